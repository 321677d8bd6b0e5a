"""The image loop's pose-graph model of its odometry and detections (docs/calibration.md, "The
pose graph's model for image runs"): a heading bias that decays beyond the fixes that measured it
(Gauss-Markov, not a random walk kept for ever), and a detected rock centre's bias shared by every
detection of that rock (one biased rock seen many times counts about once)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.fusion.factors import BiasWalkFactor, StateLayout, bias_transition
from lunarloc.fusion.posegraph import FusionConfig, OdometryNoise, PoseGraph
from lunarloc.online.loop import image_loop_config

DT = 0.5  # s between keyframes
SPEED = 0.3  # m/s


def _drive(fusion: FusionConfig, bias_rad_s: float, fixed_s: float, free_s: float) -> PoseGraph:
    """A rover driving straight along x; its odometry's heading drifts by `bias_rad_s` while
    pose fixes (every 1.5 s, exact) come, for `fixed_s` seconds, then `free_s` seconds without
    fixes during which the odometry's heading is exact. Solved over everything."""
    g = PoseGraph(fusion)
    yaw_odo, n_fixed = 0.0, int(fixed_s / DT)
    for k in range(n_fixed + int(free_s / DT) + 1):
        t = k * DT
        x = SPEED * t
        if k:
            yaw_odo += (bias_rad_s if k <= n_fixed else 0.0) * DT
        # odometry position integrates its own (drifting) heading
        xo = x if k == 0 else g.keyframes[-1].odo_pose4[0] + SPEED * DT * math.cos(yaw_odo)
        yo = 0.0 if k == 0 else g.keyframes[-1].odo_pose4[1] + SPEED * DT * math.sin(yaw_odo)
        g.add_keyframe(t, [xo, yo, 0.0, yaw_odo])
        if k and k <= n_fixed and k % 3 == 0:
            g.add_fix(k, [x, 0.0, 0.0, 0.0], 0.01, 0.002)
            g.solve()
    g.solve()
    return g


def test_bias_transition_limits():
    rw = OdometryNoise(bias_walk_rad_s_sqrt_s=1e-4)
    tau = np.array([0.5, 2.0, 10.0])
    phi, var = bias_transition(tau, rw)
    assert np.all(phi == 1.0) and np.allclose(var, 1e-8 * tau)  # the random walk
    gm = replace(rw, bias_time_constant_s=20.0)
    phi, var = bias_transition(tau, gm)
    assert np.allclose(phi, np.exp(-tau / 20.0))
    # stationary: var(b') = phi^2 var(b) + var(w) keeps q^2 T / 2
    s2 = 1e-8 * 20.0 / 2
    assert np.allclose(phi**2 * s2 + var, s2)
    # a long correlation time tends to the random walk
    phi, var = bias_transition(tau, replace(rw, bias_time_constant_s=1e7))
    assert np.allclose(var, 1e-8 * tau, rtol=1e-5)


def test_bias_factor_residual():
    noise = OdometryNoise(bias_walk_rad_s_sqrt_s=1e-4, bias_time_constant_s=10.0)
    f = BiasWalkFactor(StateLayout(3), [0, 1], [1.0, 4.0], noise)
    phi, var = bias_transition(np.array([1.0, 4.0]), noise)
    v = np.array([[2e-4, 1e-4], [1e-4, 0.0]])
    assert np.allclose(f.residual(v)[:, 0], (v[:, 1] - phi * v[:, 0]) / np.sqrt(var))


def test_config_refuses_bad_values():
    with pytest.raises(ConfigError):
        FusionConfig(detection_bias_sigma_m=-0.01)
    with pytest.raises(ConfigError):
        FusionConfig(detection_bias_sigma_z_m=math.inf)


def test_image_loop_bias_decays_beyond_the_fixes():
    """30 s of fixes measure a 1 mrad/s heading drift, then 60 s without fixes on an odometry
    that no longer drifts: the image loop's model lets the estimated bias decay (its heading error
    at the end stays small); the random walk carried it for ever."""
    fusion = image_loop_config().fusion
    assert fusion.noise.bias_time_constant_s is not None
    g = _drive(fusion, 1e-3, 30.0, 60.0)
    n_fixed = int(30.0 / DT)
    b_fix, b_end = g.keyframes[n_fixed].bias_rad_s, g.keyframes[-1].bias_rad_s
    assert b_fix > 3e-4  # the fixes did measure the drift
    assert abs(b_end) < 0.1 * b_fix
    yaw_end = abs(g.keyframes[-1].estimate_pose4[3])
    # the random walk's estimate, for comparison: the bias kept, its heading error grown
    rw = replace(fusion, noise=replace(fusion.noise, bias_time_constant_s=None))
    g_rw = _drive(rw, 1e-3, 30.0, 60.0)
    assert abs(g_rw.keyframes[-1].bias_rad_s) > 0.5 * b_fix
    assert yaw_end < 0.5 * abs(g_rw.keyframes[-1].estimate_pose4[3])


def _standing_rover(fusion: FusionConfig) -> PoseGraph:
    """A rover standing still for 20 keyframes (loose start, exact odometry). Rock A (2, 0) is
    detected 6 cm off along x in every keyframe (the same rock, the same bias); rocks B (-2, 0),
    C (0, 2), D (0, -2) are detected exactly in the first two. The reference states the rocks
    exact (sigma 0, a simulated site's rocks.csv)."""
    fusion = replace(
        fusion,
        noise=OdometryNoise(
            start_sigma_m=10.0, start_sigma_yaw_rad=1.0, trans_floor_m=1e-5, yaw_floor_rad=1e-6
        ),
        calibrate=False,
        loss="linear",
    )
    g = PoseGraph(fusion)
    rocks = {"A": (2.0, 0, 0), "B": (-2.0, 0, 0), "C": (0, 2.0, 0), "D": (0, -2.0, 0)}
    for k in range(20):
        g.add_keyframe(float(k), [0.0, 0.0, 0.0, 0.0])
        seen = ["A"] + (["B", "C", "D"] if k < 2 else [])
        det = [np.array(rocks[r]) + (np.array([0.06, 0, 0]) if r == "A" else 0.0) for r in seen]
        g.add_landmark_observations(
            [(k, r) for r in seen],
            [k] * len(seen),
            det,
            np.zeros((len(seen), 2)),
            [rocks[r] for r in seen],
            fusion.observation_sigma_m,
            seen,
            np.zeros(len(seen)),
        )
    g.solve()
    return g


def test_image_loop_detection_bias_counts_a_rock_once():
    """Tied as 26 independent detections, rock A's 20 biased sightings pull the rover 4-5 cm off;
    the image loop's shared detection bias (3 cm per axis) counts rock A about once."""
    fusion = image_loop_config().fusion
    assert fusion.detection_bias_sigma_m > 0
    off_shared = abs(_standing_rover(fusion).keyframes[-1].estimate_pose4[0])
    independent = replace(fusion, detection_bias_sigma_m=0.0, detection_bias_sigma_z_m=0.0)
    off_indep = abs(_standing_rover(independent).keyframes[-1].estimate_pose4[0])
    assert off_indep > 0.04
    assert off_shared < 0.03
