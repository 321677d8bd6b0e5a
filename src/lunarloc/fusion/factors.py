"""The pose graph's factors: one small class per kind, each vectorised over its instances,
giving its residual in sigmas and the state columns it reads (:class:`StateLayout`); the
Jacobian sparsity and the robust loss are derived from them (see :mod:`lunarloc.fusion.posegraph`
for the model)."""

from __future__ import annotations

import numpy as np

from lunarloc.core.errors import ConfigError

__all__ = [
    "StateLayout",
    "Factor",
    "OdometryFactor",
    "BiasWalkFactor",
    "bias_transition",
    "PriorFactor",
    "PoseFixFactor",
    "LandmarkFactor",
    "SharedLandmarkFactor",
    "jacobian_sparsity",
    "robust_loss",
    "stacked_residual",
    "wrap_angle",
]


def wrap_angle(a):
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class StateLayout:
    """Indices into the full state vector ``z`` of a graph of ``K`` keyframes and ``L``
    reference landmarks: ``[x_0, y_0, z_0, psi_0, ..., x_{K-1}, ..., psi_{K-1}, b_0, ...,
    b_{K-1}, k, e_0 (3), ..., e_{L-1} (3)]`` (``e_j`` the error of reference landmark j)."""

    def __init__(self, num_keyframes: int, num_landmarks: int = 0):
        self.K = int(num_keyframes)
        self.L = int(num_landmarks)
        self.size = 5 * self.K + 1 + 3 * self.L
        self.scale = 5 * self.K

    def landmark(self, j) -> np.ndarray:
        """(n, 3) indices of the error (x, y, z) of reference landmarks ``j`` (n,)."""
        return self.scale + 1 + 3 * np.asarray(j, int).reshape(-1, 1) + np.arange(3)

    def pose(self, i) -> np.ndarray:
        """(n, 4) indices of (x, y, z, yaw) of keyframes ``i`` (n,)."""
        return 4 * np.asarray(i, int).reshape(-1, 1) + np.arange(4)

    def bias(self, i) -> np.ndarray:
        """(n,) indices of the heading biases of keyframes ``i``."""
        return 4 * self.K + np.asarray(i, int).reshape(-1)

    def active(self, first: int, calibrate: bool, landmarks=()) -> np.ndarray:
        """Indices optimised when keyframes ``first..K-1`` and reference landmarks
        `landmarks` are free (the rest held fixed)."""
        idx = np.arange(4 * first, 4 * self.K)
        if calibrate:
            idx = np.r_[idx, np.arange(4 * self.K + first, 5 * self.K), self.scale]
        if len(landmarks):
            idx = np.r_[idx, self.landmark(landmarks).ravel()]
        return idx


class Factor:
    """``n`` factors of one kind. ``columns`` (n, m) are the state indices factor ``i`` reads;
    :meth:`residual` maps their values ``z[columns]`` (n, m) to (n, dim) residuals in sigmas.
    The residual sees nothing but its columns, so the Jacobian sparsity derived from them
    (:func:`jacobian_sparsity`) cannot miss a dependency. ``reads`` (dim, m), optional,
    narrows which of the columns each residual row reads (fewer finite-difference groups);
    ``tests/test_fusion.py`` checks it against a numerical Jacobian."""

    dim: int = 0
    reads: np.ndarray | None = None  # (dim, m) bool; None: every row reads every column
    robust: bool = (
        True  # False: a Gaussian prior, kept out of the robust loss (see :func:`robust_loss`)
    )
    columns: np.ndarray

    def __len__(self) -> int:
        return len(self.columns)

    def residual(self, v: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError


def _rotate_z(psi: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Rotate (n, 3) vectors by yaw ``psi`` (n,) about z."""
    c, s = np.cos(psi), np.sin(psi)
    return np.stack(
        [c * xyz[:, 0] - s * xyz[:, 1], s * xyz[:, 0] + c * xyz[:, 1], xyz[:, 2]], axis=1
    )


class OdometryFactor(Factor):
    """Edge ``i -> j``: ``Rz(-psi_i)(p_j - p_i) = k d`` and ``psi_j - psi_i = dpsi - b_i tau``.
    Columns: pose i (4), pose j (4), ``b_i``, ``k``. The translation sigma per axis is the
    distance model (``trans_floor_m``, ``trans_rel``) or, with ``measured_step_scale`` set, the
    odometry's own sigma of the edge (`step_sigma_m`, (n,), NaN where it states none)."""

    dim = 4
    #                  x_i y_i z_i psi_i x_j y_j z_j psi_j b_i k
    # yaw
    reads = np.array(
        [
            [1, 1, 0, 1, 1, 1, 0, 0, 0, 1],  # along-track (heading frame of i)
            [1, 1, 0, 1, 1, 1, 0, 0, 0, 1],  # cross-track
            [0, 0, 1, 0, 0, 0, 1, 0, 0, 1],  # vertical
            [0, 0, 0, 1, 0, 0, 0, 1, 1, 0],
        ],
        bool,
    )

    def __init__(
        self, layout: StateLayout, i, odo_pose4: np.ndarray, moving_time_s, noise, step_sigma_m=None
    ):
        i = np.asarray(i, int).reshape(-1)
        a, b = odo_pose4[i], odo_pose4[i + 1]
        self.d = _rotate_z(-a[:, 3], b[:, :3] - a[:, :3])  # odometry step in the heading frame of i
        self.dpsi = wrap_angle(b[:, 3] - a[:, 3])
        self.tau = np.asarray(moving_time_s, float).reshape(-1)
        sigma = np.sqrt(
            noise.trans_floor_m**2 + (noise.trans_rel * np.linalg.norm(self.d, axis=1)) ** 2
        )
        if step_sigma_m is not None and noise.measured_step_scale is not None:
            # the odometry's own sigma of the step (NaN: none stated, the distance model)
            m = np.asarray(step_sigma_m, float).reshape(-1)
            own = np.sqrt(noise.trans_floor_m**2 + (noise.measured_step_scale * m) ** 2)
            sigma = np.where(np.isfinite(m), own, sigma)
        self.sigma_m = sigma[:, None]
        self.sigma_yaw = np.sqrt(noise.yaw_floor_rad**2 + noise.yaw_noise_rad_sqrt_s**2 * self.tau)
        self.columns = np.column_stack(
            [layout.pose(i), layout.pose(i + 1), layout.bias(i), np.full(len(i), layout.scale)]
        )

    def residual(self, v):
        local = _rotate_z(-v[:, 3], v[:, 4:7] - v[:, 0:3])
        k, bias = v[:, 9:10], v[:, 8]
        dyaw = wrap_angle(v[:, 7] - v[:, 3] - (self.dpsi - bias * self.tau)) / self.sigma_yaw
        return np.column_stack([(local - k * self.d) / self.sigma_m, dyaw])


class BiasWalkFactor(Factor):
    """Heading-bias process over an edge of ``tau`` seconds of motion: a random walk
    ``b_{i+1} - b_i ~ N(0, q^2 tau)`` (``q`` = ``bias_walk_rad_s_sqrt_s``), or, with a finite
    correlation time ``T`` (``bias_time_constant_s``), the first-order Gauss-Markov process with
    the same driving noise: ``b_{i+1} - phi b_i ~ N(0, q^2 T / 2 (1 - phi^2))``, ``phi =
    exp(-tau / T)``: a bias the odometry shows for a while, whose estimate decays back to 0
    beyond the fixes that measured it instead of being extrapolated for ever (the random walk is
    its limit ``T -> inf``). Columns: ``b_i``, ``b_{i+1}``."""

    dim = 1

    def __init__(self, layout: StateLayout, i, moving_time_s, noise):
        i = np.asarray(i, int).reshape(-1)
        tau = np.maximum(np.asarray(moving_time_s, float).reshape(-1), 1e-3)
        self.phi, var = bias_transition(tau, noise)
        T = noise.bias_time_constant_s
        # the random walk's sigma as it always was computed (its solves unchanged to the bit)
        rw = T is None or not np.isfinite(T)
        self.sigma = noise.bias_walk_rad_s_sqrt_s * np.sqrt(tau) if rw else np.sqrt(var)
        self.columns = np.column_stack([layout.bias(i), layout.bias(i + 1)])

    def residual(self, v):
        return ((v[:, 1] - self.phi * v[:, 0]) / self.sigma)[:, None]


def bias_transition(tau_s, noise) -> tuple[np.ndarray, np.ndarray]:
    """(phi, variance) of the heading bias over ``tau_s`` seconds of motion: ``b' = phi b + w``,
    ``w ~ N(0, variance)`` (see :class:`BiasWalkFactor`)."""
    tau = np.asarray(tau_s, float)
    q2 = float(noise.bias_walk_rad_s_sqrt_s) ** 2
    T = noise.bias_time_constant_s
    if T is None or not np.isfinite(T):
        return np.ones_like(tau), q2 * tau
    phi = np.exp(-tau / float(T))
    return phi, q2 * float(T) / 2 * (1 - phi**2)


class PriorFactor(Factor):
    """Gaussian prior ``z[c] ~ N(mean, sigma^2)`` on single state values (calibration priors:
    the odometry scale, the first heading bias). Columns: the one value."""

    dim = 1

    def __init__(self, columns, mean, sigma, robust: bool = True):
        self.columns = np.asarray(columns, int).reshape(-1, 1)
        self.mean = np.asarray(mean, float).reshape(-1)
        self.sigma = np.asarray(sigma, float).reshape(-1)
        self.robust = robust

    def residual(self, v):
        return ((v[:, 0] - self.mean) / self.sigma)[:, None]


class PoseFixFactor(Factor):
    """Keyframe pose = a known (x, y, z, yaw) with position and yaw sigmas: a global fix, or
    the anchor of the first keyframe at the start pose. Columns: the keyframe's pose (4)."""

    dim = 4
    reads = np.eye(4, dtype=bool)  # x, y, z, yaw each against its own value

    def __init__(self, layout: StateLayout, keyframes, pose4, sigma_m, sigma_yaw_rad):
        kf = np.asarray(keyframes, int).reshape(-1)
        self.pose4 = np.asarray(pose4, float).reshape(-1, 4)
        self.sigma_m = np.asarray(sigma_m, float).reshape(-1, 1)
        self.sigma_yaw = np.asarray(sigma_yaw_rad, float).reshape(-1)
        self.columns = layout.pose(kf)

    def residual(self, v):
        return np.column_stack(
            [
                (v[:, :3] - self.pose4[:, :3]) / self.sigma_m,
                wrap_angle(v[:, 3] - self.pose4[:, 3]) / self.sigma_yaw,
            ]
        )


class LandmarkFactor(Factor):
    """Detection ``p_rover`` at keyframe ``k`` is reference landmark ``target``:
    ``p_k + Rz(psi_k) R_rp p_rover = target`` (``R_rp`` the keyframe's odometry roll/pitch,
    applied once here). Columns: the keyframe's pose (4)."""

    dim = 3
    # x and y turn with yaw; z does not
    reads = np.array([[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 0]], bool)

    def __init__(self, layout: StateLayout, keyframes, p_rover, roll_pitch_rad, targets, sigma_m):
        kf = np.asarray(keyframes, int).reshape(-1)
        p = np.asarray(p_rover, float).reshape(-1, 3)
        rp = np.asarray(roll_pitch_rad, float).reshape(-1, 2)
        # level the detection by roll and pitch: R = Rz(yaw) Ry(pitch) Rx(roll)
        cr, sr, cp, sp = np.cos(rp[:, 0]), np.sin(rp[:, 0]), np.cos(rp[:, 1]), np.sin(rp[:, 1])
        y1 = cr * p[:, 1] - sr * p[:, 2]
        z1 = sr * p[:, 1] + cr * p[:, 2]
        self.p_level = np.stack([cp * p[:, 0] + sp * z1, y1, -sp * p[:, 0] + cp * z1], axis=1)
        self.targets = np.asarray(targets, float).reshape(-1, 3)
        self.sigma_m = np.asarray(sigma_m, float).reshape(-1, 1)
        self.columns = layout.pose(kf)

    def residual(self, v):
        return (_rotate_z(v[:, 3], self.p_level) + v[:, :3] - self.targets) / self.sigma_m


class SharedLandmarkFactor(LandmarkFactor):
    """Tie to a reference landmark whose error ``e`` is in the state, shared by all its ties:
    ``p_k + Rz(psi_k) R_rp p_rover = target + e`` with the detection's own sigma. Columns: the
    keyframe's pose (4), the landmark's error (3). Its prior ``e ~ N(0, sigma_ref^2)`` is a
    :class:`PriorFactor` per component."""

    #                  x  y  z  psi ex ey ez
    reads = np.array([[1, 0, 0, 1, 1, 0, 0], [0, 1, 0, 1, 0, 1, 0], [0, 0, 1, 0, 0, 0, 1]], bool)

    def __init__(
        self, layout: StateLayout, keyframes, landmarks, p_rover, roll_pitch_rad, targets, sigma_m
    ):
        super().__init__(layout, keyframes, p_rover, roll_pitch_rad, targets, sigma_m)
        self.columns = np.column_stack([self.columns, layout.landmark(landmarks)])

    def residual(self, v):
        return (
            _rotate_z(v[:, 3], self.p_level) + v[:, :3] - self.targets - v[:, 4:7]
        ) / self.sigma_m


def jacobian_sparsity(factors: list[Factor], active: np.ndarray, state_size: int):
    """(rows, len(active)) CSR pattern: residual row ``c`` of factor ``i`` depends on the
    active ones of ``columns[i]`` (those ``reads[c]`` selects), nothing else."""
    from scipy.sparse import coo_matrix

    col_of = np.full(state_size, -1)
    col_of[active] = np.arange(len(active))
    rows, cols, r0 = [], [], 0
    for f in factors:
        n, m = f.columns.shape
        reads = np.ones((f.dim, m), bool) if f.reads is None else f.reads
        c, j = np.nonzero(reads)  # row within the factor, column it reads
        rows.append((r0 + f.dim * np.arange(n)[:, None] + c).ravel())
        cols.append(col_of[f.columns[:, j]].ravel())
        r0 += n * f.dim
    rr, cc = np.concatenate(rows), np.concatenate(cols)
    keep = cc >= 0
    S = coo_matrix(
        (np.ones(int(keep.sum())), (rr[keep], cc[keep])), shape=(r0, len(active))
    ).tocsr()
    S.data[:] = 1.0
    return S


def _loss_rho(name: str, z: np.ndarray) -> np.ndarray:
    """(3, n) rho(z), rho'(z), rho''(z) of scipy's named robust losses (z = squared scaled
    residual)."""
    if name == "linear":
        return np.stack([z, np.ones_like(z), np.zeros_like(z)])
    if name == "soft_l1":
        t = 1 + z
        return np.stack([2 * (t**0.5 - 1), t**-0.5, -0.5 * t**-1.5])
    if name == "huber":
        big = z > 1
        r = np.sqrt(np.where(big, z, 1.0))
        return np.stack(
            [
                np.where(big, 2 * r - 1, z),
                np.where(big, 1 / r, 1.0),
                np.where(big, -0.5 / r**3, 0.0),
            ]
        )
    if name == "cauchy":
        t = 1 + z
        return np.stack([np.log1p(z), 1 / t, -1 / t**2])
    if name == "arctan":
        t = 1 + z**2
        return np.stack([np.arctan(z), 1 / t, -2 * z / t**2])
    raise ConfigError(f"loss={name!r}: use one of linear, soft_l1, huber, cauchy, arctan")


def robust_loss(factors: list[Factor], name: str):
    """The ``loss`` argument of ``least_squares`` for `factors`: the named robust loss on every
    residual, except the rows of factors that are Gaussian priors (``robust = False``: a prior
    is no measurement that can be an outlier; robust, a reference rock's error would grow
    cheaply and let the trajectory wander with its rocks), which stay quadratic. Just `name`
    when every factor is robust."""
    mask = (
        np.concatenate([np.full(len(f) * f.dim, f.robust) for f in factors])
        if factors
        else np.zeros(0, bool)
    )
    if mask.all():
        return name

    def loss(z):
        out = _loss_rho(name, z)
        out[:, ~mask] = _loss_rho("linear", z[~mask])
        return out

    return loss


def stacked_residual(factors: list[Factor], z: np.ndarray) -> np.ndarray:
    """All factors' residuals at full state ``z``, factor by factor, row-major."""
    return np.concatenate([f.residual(z[f.columns]).ravel() for f in factors])
