"""Landmark ties share their reference landmark's error (fusion.ReferenceErrorModel.SHARED):
a biased reference rock tied many times pulls the trajectory by its share, not once per tie."""

import math

import numpy as np
import pytest

from lunarloc.config.run import RunConfig
from lunarloc.core.errors import ConfigError, InputError
from lunarloc.fusion.posegraph import (
    FusionConfig,
    OdometryNoise,
    PoseGraph,
    ReferenceErrorModel,
)
from lunarloc.fusion.factors import (
    SharedLandmarkFactor,
    StateLayout,
    jacobian_sparsity,
    stacked_residual,
)

SIGMA_OBS = 0.05  # the detection's own sigma (m)
SIGMA_REF = 0.05  # each reference rock's stated sigma per axis (m)
BIAS = 0.10  # rock A's stated position is this far off along x (m)


def _standing_rover(model: ReferenceErrorModel, n_a=20, n_good=2, sigma_a=SIGMA_REF):
    """A rover standing still for `n_a` keyframes (loose start, exact odometry). Rock A (2, 0)
    is stated `BIAS` off along x and seen in every keyframe; rocks B (-2, 0), C (0, 2), D (0, -2)
    are exact and seen in the first `n_good` keyframes. Placed so that x decouples from yaw."""
    noise = OdometryNoise(
        start_sigma_m=10.0, start_sigma_yaw_rad=1.0, trans_floor_m=1e-5, yaw_floor_rad=1e-6
    )
    g = PoseGraph(FusionConfig(noise=noise, calibrate=False, loss="linear", reference_error=model))
    rocks = {
        "A": np.array([2.0, 0, 0]),
        "B": np.array([-2.0, 0, 0]),
        "C": np.array([0, 2.0, 0]),
        "D": np.array([0, -2.0, 0]),
    }
    for k in range(n_a):
        g.add_keyframe(float(k), [0.0, 0.0, 0.0, 0.0])
        seen = ["A"] + (["B", "C", "D"] if k < n_good else [])
        targets = [rocks[r] + (np.array([BIAS, 0, 0]) if r == "A" else 0.0) for r in seen]
        g.add_landmark_observations(
            [(k, r) for r in seen],
            [k] * len(seen),
            [rocks[r] for r in seen],
            np.zeros((len(seen), 2)),
            targets,
            SIGMA_OBS,
            seen,
            [sigma_a if r == "A" else SIGMA_REF for r in seen],
        )
    g.solve()
    return g


def test_a_biased_rock_tied_many_times_pulls_by_its_share_only():
    n_a, n_good = 20, 2
    shared = _standing_rover(ReferenceErrorModel.SHARED, n_a, n_good).poses()
    alone = _standing_rover(ReferenceErrorModel.INDEPENDENT, n_a, n_good).poses()
    # the exact least-squares answer with the ties' true covariance s_obs^2 I + s_ref^2 1 1^T:
    # a rock tied n times is one measurement of variance s_obs^2 / n + s_ref^2
    w_a = 1 / (SIGMA_OBS**2 / n_a + SIGMA_REF**2)
    w_good = 3 / (
        SIGMA_OBS**2 / n_good + SIGMA_REF**2
    )  # B, C and D all fix x (C and D's yaw terms cancel)
    share = BIAS * w_a / (w_a + w_good)
    assert np.all(np.abs(shared[:, 0] - share) < 2e-3), (shared[:, 0], share)
    # tied as independent, A's n ties outvote the others': the pull is n_a / (n_a + 3 n_good) of the bias
    assert np.all(np.abs(alone[:, 0] - BIAS * n_a / (n_a + 3 * n_good)) < 2e-3)
    assert alone[:, 0].min() > 2 * shared[:, 0].max()
    assert np.abs(shared[:, 1:3]).max() < 1e-6  # y, z and yaw not pulled
    assert np.abs(shared[:, 3]).max() < 1e-6


def test_each_reference_rock_counts_with_its_own_sigma():
    # rock A stated with 0.5 m sigma (a rock the reference barely knows): its 20 ties hardly pull
    n_a, n_good, sigma_a = 20, 2, 0.5
    x = _standing_rover(ReferenceErrorModel.SHARED, n_a, n_good, sigma_a).poses()[:, 0]
    w_a = 1 / (SIGMA_OBS**2 / n_a + sigma_a**2)
    w_good = 3 / (SIGMA_OBS**2 / n_good + SIGMA_REF**2)
    assert np.all(np.abs(x - BIAS * w_a / (w_a + w_good)) < 1e-3)
    assert x.max() < 0.002


def test_the_rock_error_estimate_is_stored_and_reused_in_a_window_solve():
    g = _standing_rover(ReferenceErrorModel.SHARED)
    a = g.reference_landmarks["A"]
    assert a.index == 0 and a.sigma_xyz.tolist() == [SIGMA_REF] * 3
    # the ties put the rock where the trajectory sees it: part of the bias is explained by A's error
    assert -BIAS < a.offset_xyz[0] < -0.01
    assert g.free_landmarks(len(g) - 1) == [0]  # tied to the newest keyframe
    assert g.free_landmarks(len(g)) == []


def _drive(model: ReferenceErrorModel, seed: int, sigma_ref=0.043, n_rocks=60):
    """A rover driving 30 m with drifting odometry, tied to reference rocks whose stated
    positions carry a fixed error (a LAC grid's quantisation, sigma 4.3 cm per axis) every
    keyframe they are within 2.5 m: returns the RMSE of the estimate (m)."""
    rng = np.random.default_rng(seed)
    K = 100
    yaw = np.cumsum(np.r_[0.0, rng.normal(0, 0.03, K - 1)])
    p = np.zeros((K, 3))
    for i in range(1, K):
        p[i] = p[i - 1] + 0.3 * np.array([math.cos(yaw[i - 1]), math.sin(yaw[i - 1]), 0.0])
    oy = yaw + 1e-3 * np.arange(K)  # heading drift
    o = np.zeros((K, 3))
    for i in range(1, K):
        o[i] = o[i - 1] + 1.02 * 0.3 * np.array([math.cos(oy[i - 1]), math.sin(oy[i - 1]), 0.0])
    rocks = np.column_stack(
        [rng.uniform(-2, 32, n_rocks), rng.uniform(-6, 6, n_rocks), np.zeros(n_rocks)]
    )
    rocks[:, 1] += np.interp(rocks[:, 0], p[:, 0], p[:, 1])
    stated = rocks + rng.uniform(-0.075, 0.075, rocks.shape) * [1, 1, 0]  # quantised to 15 cm cells
    g = PoseGraph(FusionConfig(reference_error=model))
    for i in range(K):
        g.add_keyframe(float(i), np.r_[o[i], oy[i]])
        near = np.flatnonzero(np.linalg.norm(rocks[:, :2] - p[i, :2], axis=1) < 2.5)
        c, s = math.cos(yaw[i]), math.sin(yaw[i])
        d = rocks[near] - p[i]
        det = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
        det += rng.normal(0, 0.02, det.shape)
        sig = np.column_stack([np.full(len(near), sigma_ref)] * 2 + [np.full(len(near), 0.01)])
        g.add_landmark_observations(
            [(i, int(j)) for j in near],
            [i] * len(near),
            det,
            np.zeros((len(near), 2)),
            stated[near],
            0.03,
            near.tolist(),
            sig,
        )
        if i % 5 == 4:
            g.solve(active_window_m=10.0)
    g.solve()
    return float(np.sqrt(np.mean(np.sum((g.poses()[:, :2] - p[:, :2]) ** 2, axis=1))))


def test_quantised_reference_rocks_mislead_independent_ties_more_than_shared_ones():
    shared = [_drive(ReferenceErrorModel.SHARED, s) for s in range(3)]
    alone = [_drive(ReferenceErrorModel.INDEPENDENT, s) for s in range(3)]
    assert np.mean(shared) < np.mean(alone)


def test_shared_ties_sparsity_covers_the_numerical_jacobian():
    g = _standing_rover(ReferenceErrorModel.SHARED, n_a=6, n_good=3)
    for k in range(len(g)):  # some motion and roll/pitch so that every read is exercised
        g.keyframes[k].estimate_pose4 = np.array([0.1 * k, 0.05 * k, 0.01 * k, 0.2 * k])
    for o in g.observations.values():
        o.roll_pitch_rad = np.array([0.05, -0.04])
    layout = StateLayout(len(g), len(g.reference_landmarks))
    first = 2
    factors = g.factors(first)
    assert any(isinstance(f, SharedLandmarkFactor) for f in factors)
    active = layout.active(first, g.config.calibrate, g.free_landmarks(first))
    S = jacobian_sparsity(factors, active, layout.size).toarray()
    z = g.state() + np.random.default_rng(0).normal(0, 0.05, layout.size)
    r0 = stacked_residual(factors, z)
    J = np.zeros_like(S)
    for j, c in enumerate(active):
        zz = z.copy()
        zz[c] += 1e-6
        J[:, j] = (stacked_residual(factors, zz) - r0) / 1e-6
    assert np.array_equal(S == 1, J != 0)


def test_bad_tie_inputs():
    g = PoseGraph()
    g.add_keyframe(0.0, [0, 0, 0, 0])
    with pytest.raises(InputError, match="landmark_sigma_xyz"):
        g.add_landmark_observations([0], [0], [[1, 0, 0]], [[0, 0]], [[1, 0, 0]], 0.05, ["r"])
    with pytest.raises(InputError, match=">= 0"):
        g.add_landmark_observations(
            [0], [0], [[1, 0, 0]], [[0, 0]], [[1, 0, 0]], 0.05, ["r"], [-0.01]
        )
    g.add_landmark_observations([0], [0], [[1, 0, 0]], [[0, 0]], [[1, 0, 0]], 0.05, ["r"], [0.02])
    with pytest.raises(InputError, match="two different positions"):
        g.add_landmark_observations(
            [1], [0], [[1, 0, 0]], [[0, 0]], [[1.5, 0, 0]], 0.05, ["r"], [0.02]
        )


def test_run_config_round_trips_the_tie_model_and_names_a_bad_key():
    cfg = RunConfig().with_options(
        loop__fusion=FusionConfig(
            reference_error=ReferenceErrorModel.INDEPENDENT, observation_sigma_m=0.04
        )
    )
    back = RunConfig.from_dict(cfg.to_dict())
    assert back == cfg and back.loop.fusion.reference_error is ReferenceErrorModel.INDEPENDENT
    assert cfg.to_dict()["loop"]["fusion"]["reference_error"] == "independent"
    assert RunConfig().loop.fusion.reference_error is ReferenceErrorModel.SHARED
    d = RunConfig().to_dict()
    d["loop"]["fusion"]["reference_error"] = "both"
    with pytest.raises(ConfigError, match=r"loop\.fusion\.reference_error"):
        RunConfig.from_dict(d)
    d["loop"]["fusion"]["reference_error"] = "shared"
    d["loop"]["fusion"]["observation_sigma_m"] = -0.05
    with pytest.raises(ConfigError, match="observation_sigma_m"):
        RunConfig.from_dict(d)


def test_the_loop_ties_detections_to_the_full_references_rocks_with_their_sigmas():
    from _loop_data import synthetic_traverse
    from lunarloc.pipeline.evaluation import DriftModel
    from lunarloc.online.loop import LoopState
    from lunarloc.io.maps import LandmarkMap
    from lunarloc.pipeline.sources import TraverseCsvSource

    rocks, trav = synthetic_traverse(length_m=12.0)
    rng = np.random.default_rng(4)
    sig_xy = rng.uniform(
        0.01, 0.05, len(rocks)
    )  # per-rock stated sigmas, as a grid or catalogue gives
    ref = LandmarkMap(
        rocks + rng.normal(0, 1, rocks.shape) * np.c_[sig_xy, sig_xy, np.zeros(len(rocks))],
        sigma_xy_m=sig_xy,
        sigma_z_m=np.full(len(rocks), 0.02),
    )
    cfg = RunConfig.for_detections()
    loop = LoopState(ref, cfg.loop, cfg.localization)
    with TraverseCsvSource(trav, DriftModel(0.1, 0.03)) as src:
        for f in src:
            loop.step(
                f.frame,
                f.time_s,
                f.T_odo_rover,
                f.detections_rover,
                f.T_map_rover_true,
                keyframe=f.keyframe,
            )
    g = loop.graph
    assert sum(a.accepted for a in loop.attempts) >= 2 and len(g.reference_landmarks) >= 5
    for (
        key,
        r,
    ) in g.reference_landmarks.items():  # keyed by the index in the full reference, not the crop's
        assert np.array_equal(r.target_xyz, ref.positions_xyz[key])
        assert r.sigma_xyz.tolist() == pytest.approx(
            [sig_xy[key], sig_xy[key], 0.02]
        )  # as the map states
    # ties made by different attempts share their rock's one error
    tied_at = {}
    for o in g.observations.values():
        tied_at.setdefault(o.landmark, set()).add(o.keyframe)
    assert max(len(k) for k in tied_at.values()) > 10
    res = loop.finish(len(loop.keyframes))
    assert res.summary()["ate_corrected"]["rmse_m"] < 0.05


def test_a_reference_stated_exact_is_tied_alone_as_before():
    g = PoseGraph()
    g.add_keyframe(0.0, [0, 0, 0, 0])
    g.add_keyframe(1.0, [0.3, 0, 0, 0])
    g.add_landmark_observations(
        [0, 1],
        [0, 1],
        [[1, 0, 0], [0.7, 0, 0]],
        np.zeros((2, 2)),
        [[1, 0, 0]] * 2,
        0.05,
        ["exact", "exact"],
        np.zeros((2, 3)),
    )
    assert g.reference_landmarks == {} and all(o.landmark is None for o in g.observations.values())
    g.add_landmark_observations(
        [2], [1], [[0.7, 1, 0]], [[0, 0]], [[1, 1, 0]], 0.05, ["grid"], [[0.043, 0.043, 0.0]]
    )
    assert (
        g.reference_landmarks["grid"].sigma_xyz[2] > 0
    )  # an axis stated exact keeps a finite prior
    assert {type(f).__name__ for f in g.factors()} >= {"LandmarkFactor", "SharedLandmarkFactor"}


def test_the_reference_error_prior_stays_out_of_the_robust_loss():
    from lunarloc.fusion.factors import PriorFactor, robust_loss

    g = _standing_rover(ReferenceErrorModel.SHARED, n_a=3, n_good=1)
    factors = g.factors()
    assert (
        robust_loss([f for f in factors if f.robust], "soft_l1") == "soft_l1"
    )  # unchanged without priors
    loss = robust_loss(factors, "soft_l1")
    rows = np.concatenate([np.full(len(f) * f.dim, f.robust) for f in factors])
    z = np.full(len(rows), 16.0)  # residuals of 4 loss scales
    rho = loss(z)
    prior = next(f for f in factors if isinstance(f, PriorFactor) and not f.robust)
    assert len(prior) == 3 * len(g.reference_landmarks)
    assert np.allclose(rho[:, ~rows], [[16.0], [1.0], [0.0]])  # quadratic: rho = z
    assert np.allclose(rho[0, rows], 2 * (np.sqrt(17.0) - 1))  # soft_l1 elsewhere
