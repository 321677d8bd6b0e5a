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
* Fix at keyframe ``j`` (from :func:`lunarloc.localization.localize.localize`): ``p_j = p_fix`` and
  ``psi_j = psi_fix`` with the fix's sigmas.
* Landmark tie (the loop's default kind of fix): a detection ``p_rover`` made at keyframe
  ``k`` is reference landmark ``r``: ``p_k + Rz(psi_k) R_rp p_rover = q_r + e_r`` with the
  detection's own sigma (``observation_sigma_m``). ``q_r`` is the landmark's position as the
  reference map states it and ``e_r ~ N(0, diag(s_xy^2, s_xy^2, s_z^2))`` its error, one
  3-vector per reference landmark, in the state and *shared by every tie to it*
  (:attr:`ReferenceErrorModel.SHARED`). A reference rock's error (a LAC grid's quantisation,
  4.3 cm per axis for a one-cell rock) is the same for all n detections tied to it, so it
  must count once per rock, not once per tie: tying each detection alone with a sigma that
  includes it would weigh one biased rock n times. Marginalising ``e_r`` out gives the n
  ties the covariance ``s_obs^2 I + s_ref^2 1 1^T`` per axis: their mean is known to
  ``sqrt(s_obs^2 / n + s_ref^2)``, their differences (what constrains the relative poses,
  the heading between keyframes) to ``s_obs``, as if the reference were exact.

Code shape: the graph keeps one :class:`Keyframe` record per keyframe (time, odometry
pose, estimate, bias, and the loop's frame, roll/pitch and detections), the fixes and the
landmark observations. A solve builds the factors touching the free keyframes, one small
class per kind (:class:`OdometryFactor`, :class:`BiasWalkFactor`, :class:`PriorFactor`,
:class:`PoseFixFactor`, :class:`LandmarkFactor`), each vectorised over its instances and
giving its residual and the state columns it reads (:class:`StateLayout`); the Jacobian
sparsity is derived from those columns (:func:`jacobian_sparsity`), never written by hand
(:mod:`lunarloc.fusion.factors`; building and solving: :mod:`lunarloc.fusion.problem`).

Estimating ``k`` and ``b`` is what keeps the trajectory right *between* fixes: after a
few fixes the odometry is calibrated and the dead-reckoned prediction drifts far less.

Gating: a fix is accepted only if its Mahalanobis distance to the current prediction
of the keyframe is within the chi-square quantile (4 DoF). The predicted covariance is
diagonal and grows with the distance and time travelled since the last accepted fix
(:class:`GateConfig`), so a fix that disagrees with odometry beyond its uncertainty is
rejected, while a long stretch without fixes widens the gate.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.fusion import problem
from lunarloc.fusion.factors import Factor, bias_transition, wrap_angle

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "OdometryNoise",
    "GateConfig",
    "ReferenceErrorModel",
    "FusionConfig",
    "Fix",
    "GateResult",
    "Keyframe",
    "LandmarkObservation",
    "ReferenceLandmark",
    "PoseGraph",
]


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
    # the bias's correlation time (s of motion): None, a random walk (kept for ever beyond the
    # last fix); finite, a Gauss-Markov bias that decays back to 0 (fusion.factors.BiasWalkFactor)
    bias_time_constant_s: float | None = None
    start_sigma_m: float = 0.01  # the first keyframe's position is known this well (m)
    start_sigma_yaw_rad: float = 0.002  # ... and its yaw (rad)
    # an edge whose odometry states its own translation sigma (Keyframe.step_sigma_m, the
    # visual odometry's per-step covariance from its PnP inliers): None ignores it (the model
    # above for every edge); a number s: that edge's translation sigma per axis is
    # sqrt(trans_floor_m^2 + (s x step_sigma_m)^2) instead of the distance model
    measured_step_scale: float | None = None

    def __post_init__(self) -> None:
        s = self.measured_step_scale
        if s is not None and (
            isinstance(s, bool) or not isinstance(s, (int, float)) or not 0 < s < math.inf
        ):
            raise ConfigError(f"measured_step_scale={s!r} must be None or positive and finite")


@dataclass(frozen=True)
class GateConfig:
    """Chi-square gate on fixes: predicted drift covariance grows with distance and time."""

    enabled: bool = True
    probability: float = 0.999  # chi-square quantile (4 DoF) a consistent fix stays within
    base_sigma_m: float = 0.05  # position sigma right after an accepted fix (m)
    rate_m_per_m: float = (
        0.05  # added position sigma per metre travelled since then (5 % of distance)
    )
    base_sigma_yaw_deg: float = 0.5  # yaw sigma right after an accepted fix
    yaw_rate_deg_per_s: float = 0.05  # added yaw sigma per second since then (3 deg/min)
    yaw_rate_deg_per_m: float = 0.5  # added yaw sigma per metre since then

    def threshold(self) -> float:
        from scipy.stats import chi2

        return float(chi2.ppf(self.probability, 4))


MIN_REFERENCE_SIGMA_M = 1e-4
"""Floor of a shared reference error's sigma on an axis the map states exact (0) while others
are not: keeps its prior finite."""


class ReferenceErrorModel(str, enum.Enum):
    """How the reference landmarks' own position error enters the landmark ties."""

    # one error 3-vector per reference landmark, shared by its ties, prior its stated sigma
    SHARED = "shared"
    INDEPENDENT = (
        "independent"  # each tie alone with observation_sigma_m; the reference's sigma is ignored
    )


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
    observation_sigma_m: float = (
        0.05  # landmark tie: the detection's own error (m; INDEPENDENT: and the reference's)
    )
    # how a reference landmark's own error enters its ties
    reference_error: ReferenceErrorModel = ReferenceErrorModel.SHARED
    # the detected centre's own bias, shared by every detection of one rock (1-sigma per axis,
    # horizontal and vertical, m): added in quadrature to the reference's stated sigma of the
    # landmark the detections are tied to (SHARED ties; 0: the detections are independent)
    detection_bias_sigma_m: float = 0.0
    detection_bias_sigma_z_m: float = 0.0

    def __post_init__(self) -> None:
        if not 0 < self.gate.probability < 1:
            raise ConfigError("gate.probability must be in (0, 1)")
        if self.min_fix_sigma_m <= 0 or self.min_fix_sigma_yaw_deg <= 0:
            raise ConfigError("fix sigma floors must be positive")
        o = self.observation_sigma_m
        if isinstance(o, bool) or not isinstance(o, (int, float)) or not 0 < o < math.inf:
            raise ConfigError(f"observation_sigma_m={o!r} must be positive and finite")
        for name in ("detection_bias_sigma_m", "detection_bias_sigma_z_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < math.inf:
                raise ConfigError(f"{name}={v!r} must be >= 0 and finite")
        try:
            object.__setattr__(self, "reference_error", ReferenceErrorModel(self.reference_error))
        except ValueError:
            raise ConfigError(
                f"reference_error={self.reference_error!r}: use one of "
                f"{', '.join(m.value for m in ReferenceErrorModel)}"
            ) from None

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


@dataclass(eq=False)
class Keyframe:
    """One keyframe: the record the loop and the pose graph share.

    Set by the graph: ``index``, ``t_s``, ``odo_pose4`` (odometry x, y, z m and yaw rad in the
    odometry frame), ``moving_time_s`` (time moving since the previous keyframe),
    ``distance_m`` (odometry distance from keyframe 0, summed keyframe to keyframe) and the
    current estimate ``estimate_pose4`` (x, y, z, yaw in the map = reference frame) with the
    heading bias ``bias_rad_s``, both rewritten by :meth:`PoseGraph.solve`.
    Carried for the loop, unused by the graph: ``frame`` (its frame number),
    ``roll_pitch_rad`` (odometry roll and pitch; gravity-fixed), ``detections_rover``
    ((N, 3) rock centres in the rover frame) and ``path_m`` (the loop's odometry path
    length, summed frame to frame, which differs from ``distance_m``). ``step_sigma_m``: the
    1-sigma (m, per axis) the odometry itself states for its step from the previous keyframe
    (the visual odometry's, from its PnP inliers), None where it states none; the odometry
    edge uses it when ``OdometryNoise.measured_step_scale`` is set.
    """

    index: int
    t_s: float
    odo_pose4: np.ndarray
    estimate_pose4: np.ndarray
    moving_time_s: float = 0.0
    distance_m: float = 0.0
    bias_rad_s: float = 0.0
    frame: int | None = None
    roll_pitch_rad: tuple[float, float] = (0.0, 0.0)
    detections_rover: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    path_m: float | None = None
    step_sigma_m: float | None = None  # the odometry's own sigma of the step ending here (m)

    @property
    def T_odo_rover(self) -> np.ndarray:
        """(4, 4) odometry pose of the keyframe (``odo_pose4`` with its roll and pitch)."""
        from lunarloc.core.geometry import pose_to_matrix

        x, y, z, yaw = self.odo_pose4
        return pose_to_matrix(x, y, z, self.roll_pitch_rad[0], self.roll_pitch_rad[1], yaw)

    @property
    def T_map_odo(self) -> np.ndarray:
        """(4, 4) correction near this keyframe: maps odometry-frame points to the map frame
        (rotation about z by the yaw correction about the origin, then the translation that
        puts the odometry position on the estimate)."""
        dpsi = float(wrap_angle(self.estimate_pose4[3] - self.odo_pose4[3]))
        c, s = math.cos(dpsi), math.sin(dpsi)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:3, 3] = self.estimate_pose4[:3] - T[:3, :3] @ self.odo_pose4[:3]
        return T


@dataclass
class LandmarkObservation:
    """Detection ``p_rover`` (rover frame, m) made at keyframe ``keyframe`` is the reference
    landmark ``target_xyz`` (map frame, m); ``roll_pitch_rad`` is the keyframe's odometry
    roll and pitch."""

    keyframe: int
    p_rover: np.ndarray
    roll_pitch_rad: np.ndarray
    target_xyz: np.ndarray
    sigma_m: float
    landmark: object = (
        None  # the reference landmark's key (:class:`ReferenceLandmark`); None: tied alone
    )


@dataclass
class ReferenceLandmark:
    """A reference landmark that detections are tied to: its stated position ``target_xyz``
    (map frame, m), the 1-sigma of that position per axis ``sigma_xyz`` (x, y, z; m), its index
    ``index`` among the graph's reference landmarks (its columns in the state) and the current
    estimate of its error ``offset_xyz`` (true = stated + offset), rewritten by every solve."""

    index: int
    target_xyz: np.ndarray
    sigma_xyz: np.ndarray
    offset_xyz: np.ndarray = field(default_factory=lambda: np.zeros(3))


# ---------------------------------------------------------------------------- the graph
class PoseGraph:
    """Incremental 4-DoF pose graph (see module docstring).

    Use: ``add_keyframe`` for every keyframe (odometry pose, time), ``gate`` and
    ``add_fix`` when a localization succeeds (or ``add_landmark_observations``), ``solve``
    to re-optimise; ``keyframes`` holds one :class:`Keyframe` record each, ``poses()`` the
    current (x, y, z, yaw) of every keyframe as an array.
    """

    def __init__(self, config: FusionConfig | None = None):
        self.config = config or FusionConfig()
        self.keyframes: list[Keyframe] = []
        self.scale = 1.0
        self.fixes: list[Fix] = []
        self.observations: dict = {}  # key -> LandmarkObservation
        self.reference_landmarks: dict = {}  # landmark key -> ReferenceLandmark (SHARED ties)
        self._last_fix_dist = 0.0
        self._last_fix_time = 0.0
        self.num_solves = 0
        # the last solve's Jacobian, free columns and layout (problem.solve), read by
        # newest_covariance when asked, and the covariance once computed from them
        self._solution: tuple | None = None
        self._newest_marginal: np.ndarray | None = None  # (5, 5): x, y, z, yaw, heading bias
        self._solved_newest: int | None = None  # the newest keyframe at the last solve

    def _marginal(self) -> np.ndarray | None:
        if self._solution is not None:
            self._newest_marginal = problem.newest_marginal(*self._solution, with_bias=True)
            self._solution = None
        return self._newest_marginal

    @property
    def newest_covariance(self) -> np.ndarray | None:
        """After a solve: the newest keyframe's (x, y, z, yaw) marginal covariance (4, 4; m^2,
        rad^2) under the graph's noise model (None before any solve, or where singular).
        Computed from the last solve's Jacobian on first use after it, so that loops which
        never read it do not pay for it."""
        C = self._marginal()
        return None if C is None else C[:4, :4].copy()

    def bias_turn_since_solve(self, i: int) -> float:
        """The heading (rad) the graph's estimated heading bias turned its prediction of keyframe
        `i` by since its last solve (``sum of b tau`` over the edges from the keyframe that was
        newest then); NaN before any solve or where `i` precedes it."""
        j = self._solved_newest
        if j is None or not 0 <= j <= i < len(self):
            return math.nan
        kfs = self.keyframes
        return float(sum(kfs[m - 1].bias_rad_s * kfs[m].moving_time_s for m in range(j + 1, i + 1)))

    def predicted_heading_variance(self, i: int) -> tuple[float, float]:
        """The heading error (rad^2) the graph's prediction of keyframe `i` grew since its last
        solve, relative to the keyframe that was newest then (j): ``(from the bias, from the
        process)``. The prediction carries the heading bias b_j the solve estimated over the
        edges j..i (``psi' = psi + dpsi - b tau``, ``b' = phi b + w``; :class:`OdometryFactor`,
        :class:`BiasWalkFactor`), so the bias's marginal variance at j (the last solve's) turns
        into ``(sum of tau phi..)^2 var(b_j)``: the first part. The second: the odometry's heading
        noise and the bias's driving noise over the same edges, as the graph models them. NaN
        for both before any solve, without calibration (no bias state), or where `i` precedes
        j."""
        C = self._marginal()
        j = self._solved_newest
        if C is None or j is None or not 0 <= j <= i < len(self) or not np.isfinite(C[4, 4]):
            return math.nan, math.nan
        nz = self.config.noise
        a, P = 0.0, np.zeros((2, 2))  # growth's coefficient on b_j; the process's (g, b) covariance
        phi_cum = 1.0
        for m in range(j + 1, i + 1):
            tau = float(self.keyframes[m].moving_time_s)
            phi, var_w = (float(v) for v in bias_transition(tau, nz))
            a += tau * phi_cum
            phi_cum *= phi
            F = np.array([[1.0, -tau], [0.0, phi]])
            Q = np.diag([nz.yaw_floor_rad**2 + nz.yaw_noise_rad_sqrt_s**2 * tau, var_w])
            P = F @ P @ F.T + Q
        return a * a * float(C[4, 4]), float(P[0, 0])

    # ------------------------------------------------------------------ building
    def __len__(self) -> int:
        return len(self.keyframes)

    def add_keyframe(
        self,
        t: float,
        odo_pose4,
        moving_time_s: float | None = None,
        *,
        frame: int | None = None,
        roll_pitch_rad=(0.0, 0.0),
        detections_rover=None,
        path_m: float | None = None,
        step_sigma_m: float | None = None,
    ) -> int:
        """Add a keyframe at time `t` (s) with odometry pose (x, y, z, yaw); returns its index.

        The new keyframe's estimate is the last estimate propagated by the calibrated
        odometry increment. `moving_time_s` is the time spent moving since the previous
        keyframe (default: the elapsed time). `frame`, `roll_pitch_rad`, `detections_rover`
        and `path_m` are carried in the :class:`Keyframe` record for the loop. `step_sigma_m`:
        the odometry's own 1-sigma (m) of the step from the previous keyframe, or None.
        """
        q = np.array(odo_pose4, float).reshape(4)
        if not np.all(np.isfinite(q)):
            raise InputError("odometry pose must be finite")
        n = len(self.keyframes)
        prev = self.keyframes[-1] if n else None
        if prev is not None and t < prev.t_s:
            raise InputError(f"keyframe time {t} is before the previous one {prev.t_s}")
        det = (
            np.zeros((0, 3))
            if detections_rover is None
            else np.asarray(detections_rover, float).reshape(-1, 3)
        )
        rp = (float(roll_pitch_rad[0]), float(roll_pitch_rad[1]))
        if step_sigma_m is not None:
            step_sigma_m = float(step_sigma_m)
            if not (math.isfinite(step_sigma_m) and step_sigma_m >= 0):
                raise InputError(f"step_sigma_m={step_sigma_m!r} must be finite and >= 0")
        if prev is None:
            kf = Keyframe(0, float(t), q, q.copy(), 0.0, 0.0, 0.0, frame, rp, det, path_m)
        else:
            tau = float(t - prev.t_s if moving_time_s is None else moving_time_s)
            c, s = math.cos(prev.odo_pose4[3]), math.sin(prev.odo_pose4[3])
            dx, dy, dz = q[:3] - prev.odo_pose4[:3]
            # odometry step in the heading frame
            d = np.array([c * dx + s * dy, -s * dx + c * dy, dz])
            dpsi = float(wrap_angle(q[3] - prev.odo_pose4[3]))
            e, b = prev.estimate_pose4, prev.bias_rad_s
            phi = float(bias_transition(tau, self.config.noise)[0])
            c, s = math.cos(e[3]), math.sin(e[3])
            kd = self.scale * d
            new = np.empty(4)
            new[:3] = e[:3] + np.array([c * kd[0] - s * kd[1], s * kd[0] + c * kd[1], kd[2]])
            new[3] = float(wrap_angle(e[3] + dpsi - b * tau))
            dist = prev.distance_m + float(np.linalg.norm(d))
            kf = Keyframe(n, float(t), q, new, tau, dist, phi * b, frame, rp, det, path_m)
            kf.step_sigma_m = step_sigma_m
        self.keyframes.append(kf)
        return n

    # ------------------------------------------------------------------ queries
    def poses(self) -> np.ndarray:
        """(K, 4) current estimates (x, y, z, yaw) of all keyframes (map frame)."""
        return np.array([kf.estimate_pose4 for kf in self.keyframes]).reshape(-1, 4)

    def pose(self, i: int) -> np.ndarray:
        return self.keyframes[i].estimate_pose4.copy()

    @property
    def biases(self) -> np.ndarray:
        return np.array([kf.bias_rad_s for kf in self.keyframes])

    def distance(self, i: int) -> float:
        """Odometry distance travelled (m) up to keyframe i."""
        return self.keyframes[i].distance_m

    def distance_since_fix(self, i: int) -> float:
        """Odometry distance (m) from the last fix (or the start) to keyframe i: what the gate's
        drift model grows with."""
        return max(self.keyframes[i].distance_m - self._last_fix_dist, 0.0)

    def predicted_sigma(self, i: int) -> tuple[float, float]:
        """Gate model: (position sigma m, yaw sigma rad) of keyframe i's prediction."""
        g = self.config.gate
        dd = max(self.keyframes[i].distance_m - self._last_fix_dist, 0.0)
        dt = max(self.keyframes[i].t_s - self._last_fix_time, 0.0)
        yaw = math.radians(
            math.hypot(g.base_sigma_yaw_deg, g.yaw_rate_deg_per_s * dt + g.yaw_rate_deg_per_m * dd)
        )
        # heading uncertainty swings the position sideways by about yaw * distance / 2
        pos = math.sqrt(g.base_sigma_m**2 + (g.rate_m_per_m * dd) ** 2 + (0.5 * yaw * dd) ** 2)
        return pos, yaw

    # ------------------------------------------------------------------ fixes
    def _fix_sigmas(self, sigma_m: float, sigma_yaw_rad: float) -> tuple[float, float]:
        c = self.config
        return max(float(sigma_m), c.min_fix_sigma_m), max(
            float(sigma_yaw_rad), math.radians(c.min_fix_sigma_yaw_deg)
        )

    def gate(self, i: int, pose4, sigma_m: float, sigma_yaw_rad: float) -> GateResult:
        """Chi-square test of a fix of keyframe i against its current prediction."""
        q = np.asarray(pose4, float).reshape(4)
        sm, sy = self._fix_sigmas(sigma_m, sigma_yaw_rad)
        pm, py = self.predicted_sigma(i)
        innov = q - self.keyframes[i].estimate_pose4
        innov[3] = float(wrap_angle(innov[3]))
        var = np.array([pm**2 + sm**2] * 3 + [py**2 + sy**2])
        d2 = float(np.sum(innov**2 / var))
        thr = self.config.gate.threshold()
        ok = (d2 <= thr) or not self.config.gate.enabled
        return GateResult(bool(ok), d2, thr, innov, pm, py)

    def _fixed_at(self, i: int) -> None:
        """A fix or observation at keyframe i restarts the gate's drift model there."""
        kf = self.keyframes[i]
        if kf.distance_m >= self._last_fix_dist:
            self._last_fix_dist, self._last_fix_time = kf.distance_m, kf.t_s

    def add_fix(self, i: int, pose4, sigma_m: float, sigma_yaw_rad: float) -> None:
        """Add a (gated) fix of keyframe i; call :meth:`solve` afterwards."""
        if not 0 <= i < len(self):
            raise InputError(f"no keyframe {i}")
        sm, sy = self._fix_sigmas(sigma_m, sigma_yaw_rad)
        self.fixes.append(Fix(i, np.asarray(pose4, float).reshape(4), sm, sy))
        self._fixed_at(i)

    def add_landmark_observations(
        self,
        keys,
        keyframes,
        p_rover,
        roll_pitch,
        targets,
        sigma_m: float,
        landmarks=None,
        landmark_sigma_xyz=None,
    ) -> None:
        """Landmark fixes: detection ``p_rover`` (rover frame) made at keyframe ``k`` is the
        reference landmark ``target`` (map frame). Residual ``T_k(p_rover) - target`` with
        ``T_k`` = (x, y, z, yaw) of the keyframe and its odometry roll/pitch, in units of the
        detection's sigma `sigma_m`. `keys` (hashable, one per observation) de-duplicate: a
        detection re-associated by a later window replaces its earlier constraint.

        `landmarks` (hashable, one per observation: which reference landmark it is tied to) and
        `landmark_sigma_xyz` ((n, 3) or (n,): that landmark's 1-sigma per axis, m) model the
        reference's own error once per landmark (``FusionConfig.reference_error`` SHARED, see
        the module docstring); without them, or with INDEPENDENT, each tie stands alone.
        Call :meth:`solve` afterwards.
        """
        kf = np.asarray(keyframes, int).reshape(-1)
        P = np.asarray(p_rover, float).reshape(-1, 3)
        RP = np.asarray(roll_pitch, float).reshape(-1, 2)
        Q = np.asarray(targets, float).reshape(-1, 3)
        if not (len(kf) == len(P) == len(RP) == len(Q) == len(keys)):
            raise InputError("landmark observations: arrays of different lengths")
        if len(kf) and (kf.min() < 0 or kf.max() >= len(self)):
            raise InputError("landmark observation of an unknown keyframe")
        shared = landmarks is not None and self.config.reference_error is ReferenceErrorModel.SHARED
        if landmarks is not None:
            landmarks = list(landmarks)
            if landmark_sigma_xyz is None:
                raise InputError(
                    "landmark observations: landmarks given without landmark_sigma_xyz"
                )
            S = np.asarray(landmark_sigma_xyz, float)
            S = np.repeat(S.reshape(-1, 1), 3, axis=1) if S.ndim == 1 else S.reshape(-1, 3)
            if not len(landmarks) == len(S) == len(kf):
                raise InputError("landmark observations: arrays of different lengths")
            if not np.all(np.isfinite(S) & (S >= 0)):
                raise InputError("landmark observations: reference sigmas must be finite and >= 0")
            c = self.config
            bias = np.array([c.detection_bias_sigma_m] * 2 + [c.detection_bias_sigma_z_m])
            S = np.sqrt(S**2 + bias**2)
        for n, (key, k, p, rp, q) in enumerate(zip(keys, kf, P, RP, Q)):
            lm = None
            if shared and np.any(S[n] > 0):  # a landmark stated exact (sigma 0) is tied alone
                lm = landmarks[n]
                ref = self.reference_landmarks.get(lm)
                if ref is None:
                    sig = np.maximum(S[n], MIN_REFERENCE_SIGMA_M)
                    self.reference_landmarks[lm] = ReferenceLandmark(
                        len(self.reference_landmarks), q.copy(), sig
                    )
                elif not np.allclose(ref.target_xyz, q):
                    raise InputError(f"reference landmark {lm!r} tied at two different positions")
            self.observations[key] = LandmarkObservation(int(k), p, rp, q, float(sigma_m), lm)
        if len(kf):
            self._fixed_at(int(kf.max()))

    @property
    def num_observations(self) -> int:
        return len(self.observations)

    # ------------------------------------------------------------------ optimisation
    def first_active(self, active_window_m: float | None) -> int:
        """First keyframe free in a solve over the last `active_window_m` metres (None: all)."""
        return problem.first_active(self, active_window_m)

    def factors(self, first: int = 0) -> list[Factor]:
        """The factors touching keyframes ``first..K-1`` (older ones are held fixed)."""
        return problem.build_factors(self, first)

    def free_landmarks(self, first: int = 0) -> list[int]:
        """Indices of the reference landmarks a solve from keyframe `first` frees."""
        return problem.free_landmarks(self, first)

    def state(self) -> np.ndarray:
        """Full state vector (see :class:`StateLayout`)."""
        return problem.state_vector(self)

    def solve(self, active_window_m: float | None = None) -> float:
        """Re-optimise the keyframes (all, or those within `active_window_m` metres of
        travel of the newest; older ones are held fixed). Returns the final cost; a no-op
        without fixes or landmark observations (:func:`lunarloc.fusion.problem.solve`)."""
        return problem.solve(self, active_window_m)

    # ------------------------------------------------------------------ interpolation
    def corrections(self) -> np.ndarray:
        """(K, 4) per-keyframe correction ``estimate - odometry`` as (dx, dy, dz, dyaw) applied
        about the odometry position: see :meth:`correction_transforms`."""
        return np.array([kf.estimate_pose4 - kf.odo_pose4 for kf in self.keyframes]).reshape(-1, 4)

    def correction_transforms(self) -> np.ndarray:
        """(K, 4, 4) ``T_map_odo`` per keyframe (:attr:`Keyframe.T_map_odo`)."""
        return np.array([kf.T_map_odo for kf in self.keyframes]).reshape(-1, 4, 4)
