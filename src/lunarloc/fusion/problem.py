"""Building and solving the pose graph's least-squares problem: the factors touching the free
keyframes (older ones held fixed), the state vector, one robust ``least_squares`` solve and
the write-back of its result into the graph's records (:class:`lunarloc.fusion.posegraph.PoseGraph`
keeps the state; this module turns it into a problem)."""

from __future__ import annotations

import logging

import numpy as np

from lunarloc.fusion.factors import (
    BiasWalkFactor,
    Factor,
    LandmarkFactor,
    OdometryFactor,
    PoseFixFactor,
    PriorFactor,
    SharedLandmarkFactor,
    StateLayout,
    jacobian_sparsity,
    robust_loss,
    stacked_residual,
    wrap_angle,
)

log = logging.getLogger("lunarloc.fusion.posegraph")

__all__ = ["first_active", "build_factors", "free_landmarks", "state_vector", "solve"]


def first_active(graph, active_window_m: float | None) -> int:
    """First keyframe free in a solve over the last `active_window_m` metres (None: all)."""
    if active_window_m is None:
        return 0
    dist = np.array([kf.distance_m for kf in graph.keyframes])
    return min(int(np.searchsorted(dist, dist[-1] - active_window_m)), len(graph) - 1)


def build_factors(graph, first: int = 0) -> list[Factor]:
    """The factors touching keyframes ``first..K-1`` (older ones are held fixed)."""
    K, nz, calib = len(graph), graph.config.noise, graph.config.calibrate
    L = StateLayout(K, len(graph.reference_landmarks))
    kfs = graph.keyframes
    e = np.arange(max(first - 1, 0), K - 1)  # odometry edges e -> e+1 touching a free keyframe
    odo = np.array([kf.odo_pose4 for kf in kfs])
    tau = np.array([kfs[i + 1].moving_time_s for i in e])
    step = None
    if nz.measured_step_scale is not None:  # the odometry's own sigmas, NaN where it has none
        step = np.array([np.nan if (s := kfs[i + 1].step_sigma_m) is None else s for i in e])
    out: list[Factor] = [OdometryFactor(L, e, odo, tau, nz, step)]
    if first == 0:
        out.append(PoseFixFactor(L, [0], odo[0], nz.start_sigma_m, nz.start_sigma_yaw_rad))
    fixes = [f for f in graph.fixes if f.keyframe >= first]
    if fixes:
        out.append(
            PoseFixFactor(
                L,
                [f.keyframe for f in fixes],
                [f.pose4 for f in fixes],
                [f.sigma_m for f in fixes],
                [f.sigma_yaw_rad for f in fixes],
            )
        )
    obs = [o for o in graph.observations.values() if o.keyframe >= first and o.landmark is None]
    if obs:
        out.append(
            LandmarkFactor(
                L,
                [o.keyframe for o in obs],
                [o.p_rover for o in obs],
                [o.roll_pitch_rad for o in obs],
                [o.target_xyz for o in obs],
                [o.sigma_m for o in obs],
            )
        )
    out += _shared_factors(graph, L, first)
    if calib:
        out.append(BiasWalkFactor(L, e, tau, nz))
        out.append(PriorFactor([L.scale], 1.0, nz.scale_sigma))
        if first == 0:
            out.append(PriorFactor(L.bias([0]), 0.0, nz.bias_sigma_rad_s))
    return out


def free_landmarks(graph, first: int = 0) -> list[int]:
    """Indices of the reference landmarks a solve from keyframe `first` frees: those tied
    to a free keyframe."""
    return sorted(
        {
            graph.reference_landmarks[o.landmark].index
            for o in graph.observations.values()
            if o.landmark is not None and o.keyframe >= first
        }
    )


def _shared_factors(graph, L: StateLayout, first: int) -> list[Factor]:
    """Ties to the reference landmarks a solve frees (with their ties from held keyframes
    too, which pin the landmark's error where the earlier trajectory put it) and the
    landmarks' priors ``e ~ N(0, sigma_ref^2)``."""
    free = set(free_landmarks(graph, first))
    if not free:
        return []
    refs = graph.reference_landmarks
    obs = [
        o
        for o in graph.observations.values()
        if o.landmark is not None and refs[o.landmark].index in free
    ]
    ties = SharedLandmarkFactor(
        L,
        [o.keyframe for o in obs],
        [refs[o.landmark].index for o in obs],
        [o.p_rover for o in obs],
        [o.roll_pitch_rad for o in obs],
        [o.target_xyz for o in obs],
        [o.sigma_m for o in obs],
    )
    lms = [r for r in refs.values() if r.index in free]
    prior = PriorFactor(
        L.landmark([r.index for r in lms]).ravel(),
        0.0,
        np.concatenate([r.sigma_xyz for r in lms]),
        robust=False,
    )
    return [ties, prior]


def state_vector(graph) -> np.ndarray:
    """Full state vector (see :class:`StateLayout`); without calibration the biases are 0
    and the scale 1."""
    calib = graph.config.calibrate
    b = [kf.bias_rad_s if calib else 0.0 for kf in graph.keyframes]
    e = np.zeros((len(graph.reference_landmarks), 3))
    for r in graph.reference_landmarks.values():
        e[r.index] = r.offset_xyz
    return np.r_[graph.poses().ravel(), b, graph.scale if calib else 1.0, e.ravel()]


def solve(graph, active_window_m: float | None = None) -> float:
    """Re-optimise the keyframes (all, or those within `active_window_m` metres of
    travel of the newest; older ones are held fixed). Returns the final cost; a no-op
    without fixes or landmark observations."""
    if (not graph.fixes and not graph.observations) or len(graph) < 2:
        return 0.0
    from scipy.optimize import least_squares

    cfg = graph.config
    first = first_active(graph, active_window_m)
    layout = StateLayout(len(graph), len(graph.reference_landmarks))
    factors = build_factors(graph, first)
    active = layout.active(first, cfg.calibrate, free_landmarks(graph, first))
    z = state_vector(graph)

    def fun(x):
        z[active] = x
        return stacked_residual(factors, z)

    res = least_squares(
        fun,
        z[active].copy(),
        jac_sparsity=jacobian_sparsity(factors, active, layout.size),
        method="trf",
        x_scale="jac",
        max_nfev=cfg.max_nfev,
        loss=robust_loss(factors, cfg.loss),
        f_scale=cfg.loss_scale,
        ftol=1e-8,
        xtol=1e-8,
        gtol=1e-8,
    )
    z[active] = res.x
    _write_back(graph, z, layout)
    graph._solution = (res.jac, active, layout)  # PoseGraph.newest_covariance, when read
    graph._solved_newest = len(graph) - 1  # ... the keyframe it is of
    graph.num_solves += 1
    log.debug(
        "pose graph: %d keyframes (%d active), %d factors (%s), cost %.3g, scale %.4f",
        len(graph),
        len(graph) - first,
        sum(len(f) for f in factors),
        ", ".join(f"{type(f).__name__} {len(f)}" for f in factors),
        res.cost,
        graph.scale,
    )
    return float(res.cost)


def newest_marginal(
    jac, active: np.ndarray, layout: StateLayout, with_bias: bool = False
) -> np.ndarray | None:
    """(4, 4) marginal covariance of the newest keyframe's (x, y, z, yaw) (m^2, rad^2) at a
    solution: the newest keyframe's block of ``(J^T J)^-1``, ``J`` the Jacobian of the residuals
    in sigmas (as ``least_squares`` returns it, scaled by the robust loss at the solution) over
    the free state; the keyframes held fixed count as known. None where it is singular.
    `with_bias`: (5, 5), its heading bias (rad/s) last, that row and column NaN where the bias
    is not free (no calibration)."""
    from scipy.sparse import csc_matrix, identity
    from scipy.sparse.linalg import splu

    pose_cols = layout.pose([layout.K - 1])[0]
    idx = np.flatnonzero(np.isin(active, pose_cols))
    if len(idx) != 4:
        return None
    bias = np.flatnonzero(active == layout.bias([layout.K - 1])[0]) if with_bias else []
    idx = np.r_[idx, bias].astype(int)
    J = csc_matrix(jac)
    H = (J.T @ J).tocsc()
    H = H + identity(H.shape[0], format="csc") * 1e-12 * max(float(H.diagonal().max()), 1.0)
    try:
        lu = splu(H)
    except RuntimeError:  # singular
        return None
    E = np.zeros((H.shape[0], len(idx)))
    E[idx, np.arange(len(idx))] = 1.0
    C = lu.solve(E)[idx]
    C = 0.5 * (C + C.T)
    if not (np.all(np.isfinite(C)) and np.all(np.diag(C) > 0)):
        return None
    if not with_bias:
        return C
    out = np.full((5, 5), np.nan)
    out[: len(idx), : len(idx)] = C
    return out


def _write_back(graph, z: np.ndarray, layout: StateLayout) -> None:
    P = z[: 4 * layout.K].reshape(-1, 4).copy()
    P[:, 3] = wrap_angle(P[:, 3])
    calib = graph.config.calibrate
    B = z[layout.bias(np.arange(layout.K))]
    for kf, p, b in zip(graph.keyframes, P, B):
        kf.estimate_pose4 = p
        if calib:
            kf.bias_rad_s = float(b)
    if calib:
        graph.scale = float(z[layout.scale])
    for r in graph.reference_landmarks.values():
        r.offset_xyz = z[layout.landmark(r.index)[0]].copy()
