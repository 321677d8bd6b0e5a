"""Fuse global localization fixes with odometry: a 4-DoF pose graph with self-calibration.

Why ``scipy.optimize.least_squares`` and not GTSAM: GTSAM is on PyPI (``gtsam 4.3.0``,
a 34 MB cp311 manylinux wheel that ``pip install --dry-run gtsam`` resolves here), but
the factors this graph needs are not stock ones: 4-DoF poses with gravity-fixed roll and
pitch, an odometry scale and a random-walk heading bias estimated with the trajectory,
and detections tied to reference landmarks through the keyframe's odometry roll/pitch.
In GTSAM they would be Python ``CustomFactor``s (a Python call per factor per iteration)
or C++. The graph is small (hundreds to a few thousand 4-DoF nodes, re-solved over a
sliding window of recent keyframes), and scipy's trust-region solver with a sparse
Jacobian pattern (finite differences grouped by column colouring) re-solves it in tens
of milliseconds, without another heavy binary dependency.

Model (frames: ``ref`` = reference / world map frame; poses are of the rover body)
------------------------------------------------------------------------------------
State per keyframe ``i``: position ``p_i`` (m, ref frame), yaw ``psi_i`` (rad), and the
gyro heading bias ``b_i`` (rad per second of motion); one global odometry scale ``k``.
Roll and pitch are observable from gravity and are taken from odometry as they are
(the localizer is gravity-aware), so the graph is 4-DoF (x, y, z, yaw).

* Odometry edge ``i -> i+1``: ``Rz(-psi_i) (p_{i+1} - p_i) = k * d_i`` and
  ``psi_{i+1} - psi_i = dpsi_i - b_i * tau_i``, where ``d_i`` is the odometry
  displacement expressed in the odometry heading frame of ``i``, ``dpsi_i`` the odometry
  yaw increment and ``tau_i`` the time spent moving. Sigmas grow with the step
  (``sqrt(floor^2 + (rel * |d_i|)^2)`` and ``yaw_noise * sqrt(tau_i)``).
* Bias random walk ``b_{i+1} - b_i ~ N(0, walk^2 tau_i)``; priors ``k ~ N(1, scale_sigma)``,
  ``b_0 ~ N(0, bias_sigma)``; the first keyframe is anchored at the known start pose.
* Fix at keyframe ``j`` (from :func:`lunarloc.localize.localize`): ``p_j = p_fix`` and
  ``psi_j = psi_fix`` with the fix's sigmas.

Estimating ``k`` and ``b`` is what keeps the trajectory right *between* fixes: after a
few fixes the odometry is calibrated and the dead-reckoned prediction drifts far less.

Gating: a fix is accepted only if its Mahalanobis distance to the current prediction
of the keyframe is within the chi-square quantile (4 DoF). The predicted covariance is
diagonal and grows with the distance and time travelled since the last accepted fix
(:class:`GateConfig`), so a fix that disagrees with odometry beyond its uncertainty is
rejected, while a long stretch without fixes widens the gate.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from lunarloc.errors import ConfigError, InputError

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = ["OdometryNoise", "GateConfig", "FusionConfig", "Fix", "GateResult", "PoseGraph", "wrap_angle"]


def wrap_angle(a):
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class OdometryNoise:
    """Noise of the odometry edges and the calibration priors of the pose graph."""

    trans_floor_m: float = 0.002  # translation sigma floor per edge (m)
    trans_rel: float = 0.02  # translation sigma per metre of the edge (after scale calibration)
    yaw_noise_rad_sqrt_s: float = 1e-3  # heading noise, rad per sqrt(second of motion)
    yaw_floor_rad: float = 1e-4  # heading sigma floor per edge (rad)
    scale_sigma: float = 0.05  # prior sigma of the odometry scale factor k around 1
    bias_sigma_rad_s: float = 2e-3  # prior sigma of the initial heading bias (rad/s)
    bias_walk_rad_s_sqrt_s: float = 1e-4  # heading bias random walk (rad/s per sqrt(s))
    start_sigma_m: float = 0.01  # the first keyframe's position is known this well (m)
    start_sigma_yaw_rad: float = 0.002  # ... and its yaw (rad)


@dataclass(frozen=True)
class GateConfig:
    """Chi-square gate on fixes: predicted drift covariance grows with distance and time."""

    enabled: bool = True
    probability: float = 0.999  # chi-square quantile (4 DoF) a consistent fix stays within
    base_sigma_m: float = 0.05  # position sigma right after an accepted fix (m)
    rate_m_per_m: float = 0.05  # added position sigma per metre travelled since then (5 % of distance)
    base_sigma_yaw_deg: float = 0.5  # yaw sigma right after an accepted fix
    yaw_rate_deg_per_s: float = 0.05  # added yaw sigma per second since then (3 deg/min)
    yaw_rate_deg_per_m: float = 0.5  # added yaw sigma per metre since then

    def threshold(self) -> float:
        from scipy.stats import chi2

        return float(chi2.ppf(self.probability, 4))


@dataclass(frozen=True)
class FusionConfig:
    """Pose-graph fusion of fixes and odometry."""

    noise: OdometryNoise = field(default_factory=OdometryNoise)
    gate: GateConfig = field(default_factory=GateConfig)
    calibrate: bool = True  # estimate the odometry scale and heading bias (else fixed to 1 and 0)
    min_fix_sigma_m: float = 0.02  # floor of a fix's position sigma (m)
    min_fix_sigma_yaw_deg: float = 0.2  # floor of a fix's yaw sigma
    max_nfev: int = 50  # least-squares function evaluations per solve
    loss: str = "soft_l1"  # robust loss of least_squares (residuals are in sigmas)
    loss_scale: float = 3.0  # residuals beyond ~this many sigmas lose influence
    observation_sigma_m: float = 0.05  # landmark observation: detection + reference landmark error (m)

    def __post_init__(self) -> None:
        if not 0 < self.gate.probability < 1:
            raise ConfigError("gate.probability must be in (0, 1)")
        if self.min_fix_sigma_m <= 0 or self.min_fix_sigma_yaw_deg <= 0:
            raise ConfigError("fix sigma floors must be positive")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Fix:
    """A global fix of keyframe `keyframe`: pose4 = (x, y, z, yaw) in the reference frame."""

    keyframe: int
    pose4: np.ndarray
    sigma_m: float
    sigma_yaw_rad: float


@dataclass
class GateResult:
    accepted: bool
    d2: float  # Mahalanobis distance squared
    threshold: float
    innovation: np.ndarray  # fix - prediction: (dx, dy, dz, dyaw) m, m, m, rad
    predicted_sigma_m: float
    predicted_sigma_yaw_rad: float


class PoseGraph:
    """Incremental 4-DoF pose graph (see module docstring).

    Use: ``add_keyframe`` for every keyframe (odometry pose, time), ``gate`` and
    ``add_fix`` when a localization succeeds, ``solve`` to re-optimise; ``poses()``
    gives the current (x, y, z, yaw) of every keyframe.
    """

    def __init__(self, config: FusionConfig | None = None):
        self.config = config or FusionConfig()
        self._odo: list[np.ndarray] = []  # odometry (x, y, z, yaw)
        self._t: list[float] = []
        self._tau: list[float] = []  # time moving between keyframe i-1 and i
        self._est = np.zeros((0, 4))
        self._bias = np.zeros(0)
        self.scale = 1.0
        self.fixes: list[Fix] = []
        self._last_fix_dist = 0.0
        self._last_fix_time = 0.0
        self._dist: list[float] = []  # odometry distance travelled at each keyframe
        self.num_solves = 0
        self._obs: dict = {}  # key -> (keyframe, p_rover, roll_pitch, target, sigma)

    # ------------------------------------------------------------------ building
    def __len__(self) -> int:
        return len(self._odo)

    def add_keyframe(self, t: float, odo_pose4, moving_time_s: float | None = None) -> int:
        """Add a keyframe at time `t` (s) with odometry pose (x, y, z, yaw); returns its index.

        The new keyframe's estimate is the last estimate propagated by the calibrated
        odometry increment. `moving_time_s` is the time spent moving since the previous
        keyframe (default: the elapsed time).
        """
        q = np.asarray(odo_pose4, float).reshape(4)
        if not np.all(np.isfinite(q)):
            raise InputError("odometry pose must be finite")
        n = len(self._odo)
        if n and t < self._t[-1]:
            raise InputError(f"keyframe time {t} is before the previous one {self._t[-1]}")
        tau = 0.0 if n == 0 else float(t - self._t[-1] if moving_time_s is None else moving_time_s)
        self._odo.append(q)
        self._t.append(float(t))
        self._tau.append(tau)
        if n == 0:
            self._est = q[None].copy()
            self._bias = np.zeros(1)
            self._dist.append(0.0)
        else:
            d, dpsi = self._odo_increment(n - 1)
            prev = self._est[-1]
            b = self._bias[-1]
            new = np.empty(4)
            c, s = math.cos(prev[3]), math.sin(prev[3])
            kd = self.scale * d
            new[:3] = prev[:3] + np.array([c * kd[0] - s * kd[1], s * kd[0] + c * kd[1], kd[2]])
            new[3] = float(wrap_angle(prev[3] + dpsi - b * tau))
            self._est = np.vstack([self._est, new])
            self._bias = np.append(self._bias, b)
            self._dist.append(self._dist[-1] + float(np.linalg.norm(d)))
        return n

    def _odo_increment(self, i: int) -> tuple[np.ndarray, float]:
        a, b = self._odo[i], self._odo[i + 1]
        c, s = math.cos(a[3]), math.sin(a[3])
        dx, dy, dz = b[:3] - a[:3]
        return np.array([c * dx + s * dy, -s * dx + c * dy, dz]), float(wrap_angle(b[3] - a[3]))

    # ------------------------------------------------------------------ queries
    def poses(self) -> np.ndarray:
        """(K, 4) current estimates (x, y, z, yaw) of all keyframes (ref frame)."""
        return self._est.copy()

    def pose(self, i: int) -> np.ndarray:
        return self._est[i].copy()

    @property
    def biases(self) -> np.ndarray:
        return self._bias.copy()

    def distance(self, i: int) -> float:
        """Odometry distance travelled (m) up to keyframe i."""
        return self._dist[i]

    def predicted_sigma(self, i: int) -> tuple[float, float]:
        """Gate model: (position sigma m, yaw sigma rad) of keyframe i's prediction."""
        g = self.config.gate
        dd = max(self._dist[i] - self._last_fix_dist, 0.0)
        dt = max(self._t[i] - self._last_fix_time, 0.0)
        yaw = math.radians(math.hypot(g.base_sigma_yaw_deg, g.yaw_rate_deg_per_s * dt + g.yaw_rate_deg_per_m * dd))
        # heading uncertainty swings the position sideways by about yaw * distance / 2
        pos = math.sqrt(g.base_sigma_m**2 + (g.rate_m_per_m * dd) ** 2 + (0.5 * yaw * dd) ** 2)
        return pos, yaw

    # ------------------------------------------------------------------ fixes
    def _fix_sigmas(self, sigma_m: float, sigma_yaw_rad: float) -> tuple[float, float]:
        c = self.config
        return max(float(sigma_m), c.min_fix_sigma_m), max(float(sigma_yaw_rad), math.radians(c.min_fix_sigma_yaw_deg))

    def gate(self, i: int, pose4, sigma_m: float, sigma_yaw_rad: float) -> GateResult:
        """Chi-square test of a fix of keyframe i against its current prediction."""
        q = np.asarray(pose4, float).reshape(4)
        sm, sy = self._fix_sigmas(sigma_m, sigma_yaw_rad)
        pm, py = self.predicted_sigma(i)
        innov = q - self._est[i]
        innov[3] = float(wrap_angle(innov[3]))
        var = np.array([pm**2 + sm**2] * 3 + [py**2 + sy**2])
        d2 = float(np.sum(innov**2 / var))
        thr = self.config.gate.threshold()
        ok = (d2 <= thr) or not self.config.gate.enabled
        return GateResult(bool(ok), d2, thr, innov, pm, py)

    def add_fix(self, i: int, pose4, sigma_m: float, sigma_yaw_rad: float) -> None:
        """Add a (gated) fix of keyframe i; call :meth:`solve` afterwards."""
        if not 0 <= i < len(self):
            raise InputError(f"no keyframe {i}")
        sm, sy = self._fix_sigmas(sigma_m, sigma_yaw_rad)
        self.fixes.append(Fix(i, np.asarray(pose4, float).reshape(4), sm, sy))
        if self._dist[i] >= self._last_fix_dist:
            self._last_fix_dist = self._dist[i]
            self._last_fix_time = self._t[i]

    def add_landmark_observations(self, keys, keyframes, p_rover, roll_pitch, targets, sigma_m: float) -> None:
        """Landmark fixes: detection ``p_rover`` (rover frame) made at keyframe ``k`` is the
        reference landmark ``target`` (ref frame). Residual ``T_k(p_rover) - target`` with
        ``T_k`` = (x, y, z, yaw) of the keyframe and its odometry roll/pitch. `keys` (hashable,
        one per observation) de-duplicate: a detection re-associated by a later window
        replaces its earlier constraint. Call :meth:`solve` afterwards.
        """
        kf = np.asarray(keyframes, int).reshape(-1)
        P = np.asarray(p_rover, float).reshape(-1, 3)
        RP = np.asarray(roll_pitch, float).reshape(-1, 2)
        Q = np.asarray(targets, float).reshape(-1, 3)
        if not (len(kf) == len(P) == len(RP) == len(Q) == len(keys)):
            raise InputError("landmark observations: arrays of different lengths")
        if len(kf) and (kf.min() < 0 or kf.max() >= len(self)):
            raise InputError("landmark observation of an unknown keyframe")
        for key, k, p, rp, q in zip(keys, kf, P, RP, Q):
            self._obs[key] = (int(k), p, rp, q, float(sigma_m))
        if len(kf):
            k = int(kf.max())
            if self._dist[k] >= self._last_fix_dist:
                self._last_fix_dist = self._dist[k]
                self._last_fix_time = self._t[k]

    @property
    def num_observations(self) -> int:
        return len(self._obs)

    # ------------------------------------------------------------------ optimisation
    def solve(self, active_window_m: float | None = None) -> float:
        """Re-optimise the keyframes (all, or those within `active_window_m` metres of
        travel of the newest; older ones are held fixed). Returns the final cost; a no-op
        without fixes or landmark observations."""
        if (not self.fixes and not self._obs) or len(self) < 2:
            return 0.0
        from scipy.optimize import least_squares
        from scipy.sparse import coo_matrix

        K = len(self)
        cfg = self.config
        nz = cfg.noise
        calib = cfg.calibrate
        dist = np.asarray(self._dist)
        a = 0 if active_window_m is None else int(np.searchsorted(dist, dist[-1] - active_window_m))
        a = min(a, K - 1)
        odo = np.asarray(self._odo)
        c, s = np.cos(odo[:-1, 3]), np.sin(odo[:-1, 3])
        dxyz = odo[1:, :3] - odo[:-1, :3]
        d = np.stack([c * dxyz[:, 0] + s * dxyz[:, 1], -s * dxyz[:, 0] + c * dxyz[:, 1], dxyz[:, 2]], axis=1)
        dpsi = wrap_angle(odo[1:, 3] - odo[:-1, 3])
        tau = np.asarray(self._tau[1:])
        e0 = max(a - 1, 0)  # first odometry edge touching an active keyframe
        d, dpsi, tau = d[e0:], dpsi[e0:], tau[e0:]
        ei = np.arange(e0, K - 1)
        sig_t = np.sqrt(nz.trans_floor_m**2 + (nz.trans_rel * np.linalg.norm(d, axis=1)) ** 2)[:, None]
        sig_y = np.sqrt(nz.yaw_floor_rad**2 + nz.yaw_noise_rad_sqrt_s**2 * tau)
        sig_b = nz.bias_walk_rad_s_sqrt_s * np.sqrt(np.maximum(tau, 1e-3))
        fixes = [f for f in self.fixes if f.keyframe >= a]
        fk = np.array([f.keyframe for f in fixes], int)
        fp = np.array([f.pose4 for f in fixes]).reshape(-1, 4)
        fsm = np.array([f.sigma_m for f in fixes]).reshape(-1, 1)
        fsy = np.array([f.sigma_yaw_rad for f in fixes])
        obs = [o for o in self._obs.values() if o[0] >= a]
        ok_ = np.array([o[0] for o in obs], int)
        op = np.array([o[1] for o in obs]).reshape(-1, 3)
        orp = np.array([o[2] for o in obs]).reshape(-1, 2)
        oq = np.array([o[3] for o in obs]).reshape(-1, 3)
        osg = np.array([o[4] for o in obs]).reshape(-1, 1)
        # rotate observations by roll/pitch once: R = Rz(yaw) Ry(pitch) Rx(roll)
        cr, sr, cp, sp = np.cos(orp[:, 0]), np.sin(orp[:, 0]), np.cos(orp[:, 1]), np.sin(orp[:, 1])
        y1 = cr * op[:, 1] - sr * op[:, 2]
        z1 = sr * op[:, 1] + cr * op[:, 2]
        x2 = cp * op[:, 0] + sp * z1
        z2 = -sp * op[:, 0] + cp * z1
        op_level = np.stack([x2, y1, z2], axis=1)
        start = odo[0]
        full_P = self._est.copy()
        full_b = self._bias.copy()

        # variable layout over active keyframes a..K-1: 4 pose values each, then biases, then k
        Ka = K - a

        def unpack(x):
            P = np.vstack([full_P[:a], x[: 4 * Ka].reshape(Ka, 4)])
            b = np.r_[full_b[:a], x[4 * Ka : 5 * Ka]] if calib else np.zeros(K)
            k = x[5 * Ka] if calib else 1.0
            return P, b, k

        def fun(x):
            P, b, k = unpack(x)
            p, psi = P[:, :3], P[:, 3]
            i0, i1 = ei, ei + 1
            cc, ss = np.cos(psi[i0]), np.sin(psi[i0])
            dp = p[i1] - p[i0]
            local = np.stack([cc * dp[:, 0] + ss * dp[:, 1], -ss * dp[:, 0] + cc * dp[:, 1], dp[:, 2]], axis=1)
            parts = [((local - k * d) / sig_t).ravel(),
                     wrap_angle(psi[i1] - psi[i0] - (dpsi - b[i0] * tau)) / sig_y]  # fmt: skip
            if a == 0:
                parts.append(np.r_[(p[0] - start[:3]) / nz.start_sigma_m, wrap_angle(psi[0] - start[3]) / nz.start_sigma_yaw_rad])
            if len(fk):
                parts.append(np.r_[((p[fk] - fp[:, :3]) / fsm).ravel(), wrap_angle(psi[fk] - fp[:, 3]) / fsy])
            if len(ok_):
                co, so = np.cos(psi[ok_]), np.sin(psi[ok_])
                w = np.stack([co * op_level[:, 0] - so * op_level[:, 1], so * op_level[:, 0] + co * op_level[:, 1],
                              op_level[:, 2]], axis=1) + p[ok_]  # fmt: skip
                parts.append(((w - oq) / osg).ravel())
            if calib:
                parts.append((b[i1] - b[i0]) / sig_b)
                parts.append([(b[0] / nz.bias_sigma_rad_s) if a == 0 else 0.0, (k - 1.0) / nz.scale_sigma])
            return np.concatenate(parts)

        # Jacobian sparsity in full indexing, then restricted to the active variables
        rows, cols = [], []
        r = 0

        def block(n_rows, var_lists):
            nonlocal r
            rr = r + np.arange(n_rows)
            for v in var_lists:
                rows.append(rr)
                cols.append(np.broadcast_to(np.asarray(v), (n_rows,)))
            r += n_rows

        def pv(i, comp):  # full index of pose component of keyframe i
            return 4 * i + comp

        KB, KS = 4 * K, 5 * K  # full offsets of biases and scale (virtual)
        ne = len(ei)
        for comp in range(3):
            rr_vars = [pv(ei, j) for j in range(4)] + [pv(ei + 1, j) for j in range(3)]
            if calib:
                rr_vars.append(np.full(ne, KS))
            rows_here = r + 3 * np.arange(ne) + comp
            for v in rr_vars:
                rows.append(rows_here)
                cols.append(np.asarray(v))
        r += 3 * ne
        block(ne, [pv(ei, 3), pv(ei + 1, 3)] + ([KB + ei] if calib else []))
        if a == 0:
            block(4, [np.arange(4)])
        nf = len(fk)
        if nf:
            for comp in range(3):
                rows.append(r + 3 * np.arange(nf) + comp)
                cols.append(pv(fk, comp))
            r += 3 * nf
            block(nf, [pv(fk, 3)])
        no = len(ok_)
        if no:
            for comp in range(3):
                rr_o = r + 3 * np.arange(no) + comp
                for j in range(4):
                    rows.append(rr_o)
                    cols.append(pv(ok_, j))
            r += 3 * no
        if calib:
            block(ne, [KB + ei, KB + ei + 1])
            rows.append(np.array([r, r + 1]))
            cols.append(np.array([KB, KS]))
            r += 2
        rr, cc = np.concatenate(rows), np.concatenate(cols).astype(int)
        # map full variable index -> active index (or -1 when held fixed)
        n_full = 5 * K + 1
        amap = np.full(n_full, -1)
        amap[4 * a : 4 * K] = np.arange(4 * Ka)
        if calib:
            amap[KB + a : KB + K] = 4 * Ka + np.arange(Ka)
            amap[KS] = 5 * Ka
        n_var = 5 * Ka + 1 if calib else 4 * Ka
        m = amap[cc]
        keep = m >= 0
        S = coo_matrix((np.ones(keep.sum()), (rr[keep], m[keep])), shape=(r, n_var)).tocsr()
        S.data[:] = 1.0
        x0 = full_P[a:].ravel()
        if calib:
            x0 = np.r_[x0, full_b[a:], self.scale]
        res = least_squares(fun, x0, jac_sparsity=S, method="trf", x_scale="jac", max_nfev=cfg.max_nfev,
                            loss=cfg.loss, f_scale=cfg.loss_scale, ftol=1e-8, xtol=1e-8, gtol=1e-8)  # fmt: skip
        P, b, k = unpack(res.x)
        P = P.copy()
        P[:, 3] = wrap_angle(P[:, 3])
        self._est = P
        if calib:
            self._bias = np.asarray(b, float).copy()
            self.scale = float(k)
        self.num_solves += 1
        log.debug("pose graph: %d keyframes (%d active), %d fixes, %d observations, cost %.3g, scale %.4f",
                  K, Ka, len(fixes), len(obs), res.cost, self.scale)  # fmt: skip
        return float(res.cost)

    # ------------------------------------------------------------------ interpolation
    def corrections(self) -> np.ndarray:
        """(K, 4) per-keyframe correction ``estimate - odometry`` as (dx, dy, dz, dyaw) applied
        about the odometry position: see :meth:`apply_correction`."""
        return np.asarray(self._est) - np.asarray(self._odo)

    def correction_transforms(self) -> np.ndarray:
        """(K, 4, 4) ``T_est_odo`` per keyframe: maps odometry-frame points near keyframe i to the
        estimate (reference) frame (rotation about z by the yaw correction, then translation)."""
        est = self._est
        odo = np.asarray(self._odo)
        dpsi = wrap_angle(est[:, 3] - odo[:, 3])
        c, s = np.cos(dpsi), np.sin(dpsi)
        T = np.tile(np.eye(4), (len(est), 1, 1))
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
        rot_o = np.einsum("kij,kj->ki", T[:, :3, :3], odo[:, :3])
        T[:, :3, 3] = est[:, :3] - rot_o
        return T
