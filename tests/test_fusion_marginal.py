"""The pose graph's marginal covariance of its newest keyframe (PoseGraph.newest_covariance), what
OnlineLocalizer's stated covariance restarts from at a fix: exact on a linear graph, and
calibrated (NEES) on graphs drawn from the image loop's model of its detections, where the
former model (each detection independent) is over-confident."""

import math
from dataclasses import replace

import numpy as np
import pytest

from lunarloc.fusion.posegraph import FusionConfig, OdometryNoise, PoseGraph
from lunarloc.online.loop import image_loop_config
from lunarloc.pipeline.nees_online import NEES_68, NEES_997, nees


def test_linear_graph_marginal_is_exact():
    """Start anchored (sigma a), one odometry edge (sigma e), a pose fix of the second keyframe
    (sigma f): its x variance is 1 / (1 / (a^2 + e^2) + 1 / f^2)."""
    a, f = 0.03, 0.02
    noise = OdometryNoise(start_sigma_m=a, trans_floor_m=0.01, trans_rel=0.0)
    g = PoseGraph(FusionConfig(noise=noise, calibrate=False, loss="linear", min_fix_sigma_m=f))
    g.add_keyframe(0.0, [0.0, 0.0, 0.0, 0.0])
    g.add_keyframe(1.0, [1.0, 0.0, 0.0, 0.0])
    assert g.newest_covariance is None
    g.add_fix(1, [1.0, 0.0, 0.0, 0.0], f, math.radians(0.2))
    g.solve()
    C = g.newest_covariance
    assert C.shape == (4, 4) and np.allclose(C, C.T)
    expect = 1.0 / (1.0 / (a**2 + 0.01**2) + 1.0 / f**2)
    assert math.isclose(C[0, 0], expect, rel_tol=1e-3)
    assert math.isclose(C[2, 2], expect, rel_tol=1e-3)


def _draw(fusion: FusionConfig, rng) -> tuple[np.ndarray, np.ndarray]:
    """A rover driving 6 m along x (keyframes every 0.15 m, odometry with 2 % per-edge noise and
    a heading random walk), seeing 8 rocks each from 6-12 keyframes; each rock's detections share
    a centre bias (3 cm horizontal, 2.5 cm vertical per axis) and carry their own error (3 cm,
    1.8 cm vertical): the error sizes measured on LAC-map sites 286-290. Returns the newest
    keyframe's position error and the graph's marginal covariance of it."""
    n = 40
    truth = np.column_stack([np.arange(n) * 0.15, np.zeros(n), np.zeros(n), np.zeros(n)])
    odo = truth.copy()
    step = np.diff(truth[:, :3], axis=0)
    step += rng.normal(0, 0.003, step.shape)
    odo[1:, :3] = np.cumsum(step, axis=0)
    odo[1:, 3] = np.cumsum(rng.normal(0, 7e-4, n - 1))
    g = PoseGraph(fusion)
    for k in range(n):
        g.add_keyframe(0.5 * k, odo[k])
    rocks = np.column_stack(
        [rng.uniform(0, 8, 8), rng.choice([-1, 1], 8) * rng.uniform(1, 3, 8), np.zeros(8)]
    )
    keys, kfs, det, tgt, lms = [], [], [], [], []
    for r, q in enumerate(rocks):
        bias = rng.normal(0, [0.03, 0.03, 0.025])
        near = np.flatnonzero(np.abs(truth[:, 0] - q[0] + 2.5) < 1.5)
        for k in near:
            c, s = math.cos(truth[k, 3]), math.sin(truth[k, 3])
            d = q + bias + rng.normal(0, [0.03, 0.03, 0.018]) - truth[k, :3]
            keys.append((k, r))
            kfs.append(k)
            det.append([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
            tgt.append(q)
            lms.append(r)
    g.add_landmark_observations(
        keys,
        kfs,
        det,
        np.zeros((len(kfs), 2)),
        tgt,
        fusion.observation_sigma_m,
        lms,
        np.zeros(len(kfs)),
    )
    g.solve()
    return g.keyframes[-1].estimate_pose4[:3] - truth[-1, :3], g.newest_covariance[:3, :3]


def _shares(fusion: FusionConfig, draws: int = 60) -> tuple[float, float]:
    rng = np.random.default_rng(7)
    E, C = zip(*(_draw(fusion, rng) for _ in range(draws)))
    v = nees(E, C)
    return float(np.mean(v < NEES_68)), float(np.mean(v < NEES_997))


def test_image_loop_marginal_is_calibrated_where_the_former_model_was_not():
    fusion = replace(image_loop_config().fusion, loss="linear")
    core, tail = _shares(fusion)
    assert 0.55 <= core <= 0.85 and tail >= 0.95, (core, tail)
    former = replace(fusion, detection_bias_sigma_m=0.0, detection_bias_sigma_z_m=0.0)
    core0, _ = _shares(former)
    assert core0 < 0.5, core0


def test_predicted_heading_variance_propagates_the_bias_marginal():
    """After a solve, the heading the graph predicts for later keyframes grows by the bias's
    marginal variance times the time carried squared (random walk: the sum of the edges' moving
    times), plus the odometry's heading noise and the bias walk over those edges; NaN before
    any solve and for a keyframe before the solved one."""
    noise = OdometryNoise(
        yaw_noise_rad_sqrt_s=1e-3, yaw_floor_rad=1e-4, bias_walk_rad_s_sqrt_s=1e-4
    )
    g = PoseGraph(FusionConfig(noise=noise, calibrate=True, loss="linear"))
    for k in range(6):
        g.add_keyframe(2.0 * k, [0.3 * k, 0.0, 0.0, 0.0])
    assert all(math.isnan(v) for v in g.predicted_heading_variance(5))
    for k in (2, 5):
        g.add_fix(k, [0.3 * k, 0.0, 0.0, -0.002 * k], 0.02, math.radians(0.2))
    g.solve()
    taus = [1.5, 2.5, 4.0]
    t = 10.0
    for i, tau in enumerate(taus):
        t += tau
        g.add_keyframe(t, [1.5 + 0.3 * (i + 1), 0.0, 0.0, 0.0], tau)
    C5 = g._marginal()
    assert C5.shape == (5, 5) and C5[4, 4] > 0
    assert np.allclose(g.newest_covariance, C5[:4, :4])
    bias, process = g.predicted_heading_variance(len(g) - 1)
    assert math.isclose(bias, sum(taus) ** 2 * C5[4, 4], rel_tol=1e-9)
    yaw = sum(1e-4**2 + 1e-6 * tau for tau in taus)
    # a walk step w_l (variance q^2 tau_l) enters through the edges after it
    walk = sum(1e-8 * taus[m] * sum(taus[m + 1 :]) ** 2 for m in range(len(taus)))
    assert math.isclose(process, yaw + walk, rel_tol=1e-9)
    assert all(math.isnan(v) for v in g.predicted_heading_variance(3))
    # the turn its bias carried into the prediction since the solve: sum of b tau over the edges
    kfs = g.keyframes
    turn = sum(kfs[m - 1].bias_rad_s * kfs[m].moving_time_s for m in range(len(g) - 3, len(g)))
    assert g.bias_turn_since_solve(len(g) - 1) == pytest.approx(turn) and turn != 0.0
    assert math.isnan(g.bias_turn_since_solve(3))
