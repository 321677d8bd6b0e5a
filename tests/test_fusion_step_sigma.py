"""The odometry's own per-step sigma (the visual odometry's step covariance) as the pose graph's
odometry-edge sigma: the factor, the keyframe record, the loop's hand-over (synthetic, no data)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.geometry import pose_to_matrix
from lunarloc.fusion.factors import OdometryFactor, StateLayout
from lunarloc.fusion.posegraph import FusionConfig, OdometryNoise, PoseGraph
from lunarloc.io.maps import LandmarkMap
from lunarloc.online.component import OnlineLocalizer
from lunarloc.online.loop import LoopConfig, LoopState


def _odo(K=4, step=0.3):
    return np.column_stack([step * np.arange(K), np.zeros(K), np.zeros(K), np.zeros(K)])


def test_edge_sigma_is_the_stated_one_where_given_else_the_distance_model():
    nz = OdometryNoise(measured_step_scale=2.0)
    L = StateLayout(4)
    stated = np.array([0.004, np.nan, 0.0])
    f = OdometryFactor(L, np.arange(3), _odo(), np.ones(3), nz, stated)
    model = math.hypot(nz.trans_floor_m, nz.trans_rel * 0.3)
    assert f.sigma_m[:, 0] == pytest.approx(
        [math.hypot(nz.trans_floor_m, 2.0 * 0.004), model, nz.trans_floor_m]
    )
    # without the scale, stated sigmas are ignored: the distance model for every edge
    off = OdometryFactor(L, np.arange(3), _odo(), np.ones(3), OdometryNoise(), stated)
    assert off.sigma_m[:, 0] == pytest.approx([model] * 3)


def test_a_loose_stated_step_takes_the_correction():
    """Odometry 10 cm long on one step of four, which the odometry states loose: fixed at both
    ends, the graph puts the error on that step (the keyframes before it stay near the truth);
    with the distance model it spreads the error over all four steps."""
    truth = _odo(5)
    odo = truth.copy()
    odo[3:, 0] += 0.10
    stated = [None, 0.001, 0.001, 0.05, 0.001]

    def solve(scale):
        nz = OdometryNoise(measured_step_scale=scale)
        g = PoseGraph(FusionConfig(noise=nz, calibrate=False))
        for i in range(5):
            g.add_keyframe(float(i), odo[i], step_sigma_m=stated[i])
        g.add_fix(4, truth[4], 0.005, 0.002)
        g.solve()
        return g.poses()

    spread, measured = solve(None), solve(1.0)
    assert abs(spread[2, 0] - truth[2, 0]) > 0.015  # a share of the 10 cm
    assert abs(measured[2, 0] - truth[2, 0]) < 0.01


def test_bad_step_sigmas_and_scales_are_refused():
    g = PoseGraph()
    g.add_keyframe(0.0, [0, 0, 0, 0])
    with pytest.raises(InputError, match="step_sigma_m"):
        g.add_keyframe(1.0, [0.3, 0, 0, 0], step_sigma_m=-0.01)
    with pytest.raises(InputError, match="step_sigma_m"):
        g.add_keyframe(1.0, [0.3, 0, 0, 0], step_sigma_m=math.inf)
    for bad in (0.0, -1.0, math.nan, True):
        with pytest.raises(ConfigError, match="measured_step_scale"):
            OdometryNoise(measured_step_scale=bad)


def test_loop_hands_the_keyframe_the_root_sum_of_its_steps():
    ref = LandmarkMap(np.array([[5.0, 0, 0], [6.0, 1, 0], [7.0, -1, 0]]), frame="map")
    cfg = LoopConfig(localize_every_m=1e9, localize_every_s=1e9)
    cfg = replace(cfg, fusion=replace(cfg.fusion, noise=OdometryNoise(measured_step_scale=1.0)))
    loop = LoopState(ref, cfg)
    T = [pose_to_matrix(0.1 * i, 0, 0, 0, 0, 0) for i in range(8)]
    # frame: (stated sigma, keyframe)
    feed = [(None, True), (0.003, False), (0.004, True), (None, False), (None, True)]
    feed += [(0.002, False), (math.nan, False), (0.005, True)]
    for i, (s, kf) in enumerate(feed):
        loop.step(
            i, 0.5 * i, T[i], np.zeros((0, 3)) if kf else None, keyframe=kf, odometry_step_sigma_m=s
        )
    got = [kf.step_sigma_m for kf in loop.keyframes]
    # the first keyframe has no step; a keyframe whose own frame states none gets none
    assert got[0] is None and got[2] is None
    assert got[1] == pytest.approx(0.005)  # hypot(0.003, 0.004)
    assert got[3] == pytest.approx(math.hypot(0.002, 0.005))
    for bad in (-1.0, "x"):
        with pytest.raises(InputError, match="odometry_step_sigma_m"):
            loop.step(9, 5.0, T[7], np.zeros((0, 3)), keyframe=True, odometry_step_sigma_m=bad)
    assert len(loop.keyframes) == 4  # refused before anything changed


class _FakeVO:
    """Stands in for StereoVisualOdometry: 5 cm forward a pair, every step stated 3 mm (but the
    fourth, which states none, as a failed pair); counts the pairs and the covariance reads."""

    def __init__(self):
        self.pairs = 0
        self.reads = 0
        self.config = type("C", (), {"gravity_tilt_gain": 1.0})()

    def update(self, left, right, prior=None):
        self.pairs += 1
        return pose_to_matrix(0.05 * self.pairs, 0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def last_step_covariance(self):
        self.reads += 1
        return None if self.pairs in (1, 4) else np.eye(6) * 0.003**2


@pytest.mark.parametrize("scale", [None, 1.0])
def test_online_localizer_hands_its_visual_steps_sigma_to_the_graph(monkeypatch, scale):
    """OnlineLocalizer's visual odometry: with measured_step_scale set, a keyframe gets the root
    sum of squares of the steps' stated sigmas since the previous keyframe (none where one of
    them states none); without it the covariance is never read (it costs a solve a step)."""
    from lunarloc.online.component import OnlineConfig
    from lunarloc import CameraRig

    rig = CameraRig.from_calibration(160, 90, fx=114.25)
    cfg = OnlineConfig()
    noise = replace(cfg.loop.fusion.noise, measured_step_scale=scale)
    cfg = replace(cfg, loop=replace(cfg.loop, fusion=replace(cfg.loop.fusion, noise=noise)))
    ref = LandmarkMap(np.array([[5.0, 0, 0], [6.0, 1, 0], [7.0, -1, 0]]), frame="map")
    loc = OnlineLocalizer(ref, np.zeros(6), cfg, rig=rig)
    vo = _FakeVO()
    loc._vo = vo
    monkeypatch.setattr(loc, "_detect", lambda images: np.zeros((0, 3)))
    pairs_at_kf = []
    step = loc.loop.step
    monkeypatch.setattr(
        loc.loop, "step", lambda *a, **k: (pairs_at_kf.append(vo.pairs), step(*a, **k))[1]
    )
    img = np.zeros((90, 160), np.uint8)
    imu = np.array([0.0, 0.0, 1.622, 0.0, 0.0, 0.0])
    for i in range(40):
        im = img if i % 2 == 0 else None
        loc.update(0.05 * i, {"Grayscale": {"FrontLeft": im, "FrontRight": im}}, imu, 0.5, 0.0)
    got = [kf.step_sigma_m for kf in loc.loop.keyframes]
    assert len(got) >= 5 and vo.pairs == 20
    if scale is None:
        assert vo.reads == 0 and all(s is None for s in got)
        return
    assert vo.reads == vo.pairs
    assert None in got[1:] and any(s is not None for s in got[1:])
    for k in range(1, len(got)):
        a, b = pairs_at_kf[k - 1], pairs_at_kf[k]  # the pairs a+1..b are this keyframe's steps
        if 4 in range(a + 1, b + 1):
            assert got[k] is None
        else:
            assert got[k] == pytest.approx(0.003 * math.sqrt(b - a))
