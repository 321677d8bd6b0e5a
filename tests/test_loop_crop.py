"""The reference crop of a loop attempt sized by the window's odometry bounds
(LoopConfig.crop_sigma = "source") instead of the gate's drift model: the setting round-trips,
the sigma follows the gate's form with the odometry's rates, falls back to the gate's model
where no bounds are stated, and a run keeps its fixes with a smaller crop."""

import json
import math

import numpy as np
import pytest

from lunarloc.config.run import RunConfig
from lunarloc.core.errors import ConfigError
from lunarloc.online.loop import (
    CropSigma,
    LoopConfig,
    LoopState,
    OdometryBounds,
    image_localization_config,
)
from lunarloc.io.maps import LandmarkMap


def test_crop_sigma_setting_round_trips_and_refuses_bad_values():
    assert (
        LoopConfig().crop_sigma is CropSigma.GATE
    )  # the loop's own default (the real dataset's runs)
    cfg = RunConfig().with_options(loop__crop_sigma="gate")
    assert cfg.loop.crop_sigma is CropSigma.GATE
    src = RunConfig.from_dict({"loop": {"crop_sigma": "source"}})
    assert src.loop.crop_sigma is CropSigma.SOURCE
    assert (
        src.loop.window_m == RunConfig().loop.window_m
    )  # the rest of the section keeps its defaults
    for c in (cfg, src, RunConfig(), RunConfig.for_detections()):
        assert RunConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    with pytest.raises(ConfigError, match="crop_sigma"):
        RunConfig.from_dict({"loop": {"crop_sigma": "tight"}})


def _drive(
    state: LoopState, length_m: float, rocks: np.ndarray | None = None, scale_error: float = 0.0
):
    """Drive straight along +x at 0.5 m/s, a keyframe every 0.5 s, detections of `rocks` within
    5 m ahead (noise-free, rover frame); odometry `scale_error` too long."""
    dt, v = 0.5, 0.5
    for i in range(int(length_m / (v * dt)) + 1):
        x = np.array([i * v * dt, 0.0, 0.0])
        T_true = np.eye(4)
        T_true[:3, 3] = x
        T_odo = T_true.copy()
        T_odo[:3, 3] = x * (1 + scale_error)
        det = np.zeros((0, 3))
        if rocks is not None:
            d = rocks - x
            det = d[(np.linalg.norm(d[:, :2], axis=1) < 5) & (d[:, 0] > 0.5)]
        state.step(i, i * dt, T_odo, det, T_true, keyframe=True)
    return state


def test_source_sigma_follows_the_gate_form_with_the_odometry_bounds():
    ref = LandmarkMap(np.random.default_rng(0).uniform(-5, 5, (10, 3)))
    loop = LoopConfig(crop_sigma="source", localize_every_m=100.0)
    state = _drive(
        LoopState(ref, loop, image_localization_config(), odometry=OdometryBounds(0.01, 0.06)), 20.0
    )
    k = len(state.keyframes) - 1
    dd = state.graph.distance_since_fix(k)
    assert dd == pytest.approx(20.0, abs=0.3)
    g = loop.fusion.gate
    yaw = math.hypot(math.radians(g.base_sigma_yaw_deg), math.radians(0.06) * dd)
    expected = math.sqrt(g.base_sigma_m**2 + (0.01 * dd) ** 2 + (0.5 * yaw * dd) ** 2)
    gate_m, _ = state.graph.predicted_sigma(k)
    assert state.crop_sigma_m(k) == pytest.approx(expected)
    assert (
        state.crop_sigma_m(k) < gate_m / 3
    )  # visual odometry's bounds: far tighter than the gate's 5 %/m
    # no bounds stated (fitted), stated rigid (0), or crop_sigma = gate: the gate's model
    for odometry, crop in (
        (None, "source"),
        (OdometryBounds(0.0, 0.0), "source"),
        (OdometryBounds(0.01, 0.06), "gate"),
    ):
        s = _drive(
            LoopState(
                ref,
                LoopConfig(crop_sigma=crop, localize_every_m=100.0),
                image_localization_config(),
                odometry=odometry,
            ),
            20.0,
        )
        assert s.crop_sigma_m(k) == pytest.approx(s.graph.predicted_sigma(k)[0]), (odometry, crop)
    # never wider than the gate's model (a source whose bounds exceed it)
    wide = _drive(
        LoopState(ref, loop, image_localization_config(), odometry=OdometryBounds(0.5, 5.0)), 20.0
    )
    assert wide.crop_sigma_m(k) == pytest.approx(wide.graph.predicted_sigma(k)[0])


def _crop_run(crop: str):
    """A 1 %-stretched straight drive through the middle of a 70 m x 30 m rock field whose
    reference is the true rocks; visual odometry's bounds stated (1 %, 0.06 deg/m)."""
    rng = np.random.default_rng(5)
    rocks = np.column_stack(
        [rng.uniform(-20, 50, 700), rng.uniform(-15, 15, 700), rng.uniform(0.0, 0.2, 700)]
    )
    loop = LoopConfig(window_m=8.0, localize_every_m=10.0, crop_sigma=crop)
    state = LoopState(
        LandmarkMap(rocks, frame="map"),
        loop,
        image_localization_config(),
        odometry=OdometryBounds(0.01, 0.06),
    )
    _drive(state, 24.0, rocks, scale_error=0.01)
    return [a for a in state.attempts if a.landmarks >= loop.min_window_landmarks]


def test_a_source_sized_crop_keeps_the_fixes_with_fewer_reference_landmarks():
    gate, source = _crop_run("gate"), _crop_run("source")
    assert [a.frame for a in gate] == [a.frame for a in source]
    assert all(s.reference_landmarks <= g.reference_landmarks for g, s in zip(gate, source))
    assert sum(s.reference_landmarks for s in source) < 0.8 * sum(
        g.reference_landmarks for g in gate
    )
    fixes = [a for a in source if a.accepted]
    assert len(fixes) >= sum(a.accepted for a in gate) > 0
    assert all(a.fix_error_m <= max(3 * a.predicted_error_m, 0.01) for a in fixes)
