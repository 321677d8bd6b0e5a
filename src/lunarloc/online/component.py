"""The online localizer as a component a Lunar Autonomy Challenge agent calls every tick.

::

    from lunarloc import OnlineLocalizer, PlaybackAgent, load_reference
    agent = PlaybackAgent("traverse.lac")
    loc = OnlineLocalizer(load_reference("map.csv"), initial_pose=agent.get_initial_position(),
                          rig=CameraRig.from_sensors(agent.sensors()))
    loc.warm_up()                      # compile/caches before the mission clock starts
    while not agent.at_end():
        est = loc.update(agent.get_mission_time(), agent.input_data(), agent.get_imu_data(),
                         agent.get_linear_speed(), agent.get_angular_speed())
        est.T_map_rover, est.covariance, est.localized
        agent.step_frame()

Per tick (:meth:`OnlineLocalizer.update`):

1. **odometry**: the IMU is integrated every tick (:func:`lunarloc.odometry.imu.integrate_imu`,
   one step); on ticks with a front stereo pair, stereo visual odometry
   (:class:`~lunarloc.odometry.visual.StereoVisualOdometry`, with the IMU motion since the
   previous pair as its prior) replaces it, the IMU bridging the ticks in between. A caller
   with its own odometry passes ``odometry=T_odo_rover`` instead (any fixed frame ``odo``).
2. **keyframes**: an image tick becomes a keyframe when the rover moved or turned enough
   since the last one (or ``keyframe_max_interval_s`` passed); only keyframes run the rock
   detector (:class:`~lunarloc.perception.detector.Detector`).
3. **localization and fusion**: the keyframe goes to the loop state
   (:class:`lunarloc.online.loop.LoopState`: local map, association with the reference, gated
   fixes in the pose graph); the estimate is ``T_map_odo @ T_odo_rover`` with the newest
   keyframe's correction ``T_map_odo``.

Bounded memory and time: the pose graph is **re-anchored** when it holds ``max_keyframes``
keyframes: a new graph starts from the keyframes of the last ``window_m`` metres (their
current estimates become its odometry; the first one is anchored with the drift sigma
predicted there), so the history (keyframes, detections, observations, attempts) never grows
past a fixed size. The odometry calibration (scale, heading bias) restarts at each re-anchor.

Frames: ``map`` (the reference map's frame, where the initial pose is given), ``odo``
(odometry, equal to ``map`` at the start), ``rover`` (x forward, y left, z up). Metres,
radians, seconds.
"""

from __future__ import annotations

import array
import collections
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from lunarloc.core import validate
from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.geometry import invert_transform, pose_to_matrix
from lunarloc.io.lac.leaderboard import camera_name, transform_to_matrix
from lunarloc.io.maps import LandmarkMap
from lunarloc.odometry.imu import ImuOdometryConfig, ImuSamples, integrate_imu
from lunarloc.perception.camera import (
    IPEX_STEREO_BASELINE_M,
    STEREO_PAIRS,
    CameraMount,
    PinholeCamera,
    ipex_rig,
)
from lunarloc.localization.config import LocalizationConfig
from lunarloc.online.loop import (
    Attempt,
    LoopConfig,
    LoopState,
    OdometryBounds,
    image_localization_config,
    image_loop_config,
    window_centre_bias_covariance,
)

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "CameraRig",
    "OnlineConfig",
    "Estimate",
    "OnlineLocalizer",
    "camera_name",
    "as_transform_matrix",
]


# --------------------------------------------------------------------------- covariance


@dataclass(frozen=True)
class CovarianceAnchor:
    """Where the stated covariance was last known: its 3x3 position covariance (m^2, map
    frame), yaw variance (rad^2), the odometry path length there (m) and the position (map
    frame, m)."""

    position_covariance: np.ndarray
    yaw_variance: float
    path_m: float
    xyz: np.ndarray = field(default_factory=lambda: np.zeros(3))


def propagate_covariance(
    anchor: CovarianceAnchor, path_m: float, bounds: OdometryBounds, xyz=None
) -> tuple[np.ndarray, float]:
    """(3x3 position covariance m^2, yaw variance rad^2) at map-frame position `xyz` after
    ``D = path_m - anchor.path_m`` metres of odometry from the anchor, the odometry's drift
    bounds taken as one sigma (scale error s, heading drift d per metre): along the chord from
    the anchor to `xyz`, ``(s D)^2``; across it, ``sigma_yaw^2 D^2`` (the anchor's heading error
    swinging the path) ``+ (d D^2 / 2)^2`` (the drift, integrated); vertical ``(s D)^2``; yaw
    ``+ (d D)^2``. Without `xyz` (or a chord under 1 cm) the horizontal terms are split evenly
    over x and y."""
    D = max(float(path_m) - anchor.path_m, 0.0)
    s = float(bounds.scale_error)
    d = math.radians(float(bounds.heading_drift_deg_per_m))
    yaw_var = anchor.yaw_variance + (d * D) ** 2
    along = (s * D) ** 2
    across = anchor.yaw_variance * D**2 + (0.5 * d * D**2) ** 2
    P = np.array(anchor.position_covariance, float)
    c = None if xyz is None else (np.asarray(xyz, float).reshape(3) - anchor.xyz)[:2]
    if c is None or float(np.hypot(*c)) < 0.01:
        H = np.eye(2) * 0.5 * (along + across)
    else:
        u = c / float(np.hypot(*c))
        v = np.array([-u[1], u[0]])
        H = along * np.outer(u, u) + across * np.outer(v, v)
    P[:2, :2] += H
    P[2, 2] += (s * D) ** 2
    return P, float(yaw_var)


# --------------------------------------------------------------------------- inputs


def as_transform_matrix(pose, what: str = "pose") -> np.ndarray:
    """A 4x4 transform from a 4x4 array, a 6-vector (x, y, z, roll, pitch, yaw; m, rad), the
    leaderboard's right-handed ``Transform`` (``location.x/y/z``, ``rotation.roll/pitch/yaw``
    in radians, as the agent getters return it) or an object with ``matrix()`` /
    ``get_matrix()``. CARLA's own left-handed ``carla.Transform`` is refused (InputError)."""
    if hasattr(pose, "location") and hasattr(pose, "rotation"):
        # the same bounds as a matrix
        return validate.rigid_transform(transform_to_matrix(pose, what), what)
    for attr in ("matrix", "get_matrix"):
        f = getattr(pose, attr, None)
        if callable(f):
            pose = f()
            break
    try:
        raw = np.asarray(pose)
        if raw.dtype.kind not in "fiu":  # strings, bools, objects: not a pose
            raise TypeError
        a = raw.astype(float)
    except (TypeError, ValueError):
        raise InputError(
            f"{what} must be a 4x4 transform, a 6-vector or a Transform, got {type(pose).__name__}"
        ) from None
    if a.shape == (6,):
        if not np.all(np.isfinite(a)):
            raise InputError(f"{what} (x, y, z, roll, pitch, yaw) is not finite: {a.tolist()}")
        a = pose_to_matrix(*a)
    if a.shape != (4, 4):
        raise InputError(
            f"{what} must be a finite 4x4 transform or (x, y, z, roll, pitch, yaw); got shape "
            f"{a.shape}"
        )
    return validate.rigid_transform(a, what)  # orthonormal, det +1, last row 0 0 0 1


@dataclass(frozen=True)
class CameraRig:
    """Intrinsics shared by the cameras and each camera's body pose in the rover frame
    (``T_rover_cam``, LAC axes: x along the optical axis, y left, z up)."""

    camera: PinholeCamera = field(default_factory=PinholeCamera)
    T_rover_cam: Mapping[str, np.ndarray] = field(
        default_factory=lambda: {n: m.T_rover_cam for n, m in ipex_rig().items()}
    )

    def __post_init__(self) -> None:
        poses = {
            camera_name(k): as_transform_matrix(v, f"pose of camera {camera_name(k)}")
            for k, v in dict(self.T_rover_cam).items()
        }
        object.__setattr__(self, "T_rover_cam", poses)

    @classmethod
    def from_sensors(
        cls, sensors: Mapping, camera_poses: Mapping | None = None, hfov_deg: float = 70.0
    ) -> CameraRig:
        """From an agent's ``sensors()`` ({camera: {width, height, ...}}) and, optionally, the
        camera poses it reports (``get_camera_position(name)``: Transform, 4x4 or 6-vector);
        cameras without a pose get the IPEx rig's. All stereo cameras must share one size."""
        sizes = {}
        for key, c in dict(sensors).items():
            name = camera_name(key)
            try:
                if not c.get("camera_active", True) in (True, "True", "true", 1):
                    continue
                sizes[name] = (int(c.get("width", 1280)), int(c.get("height", 720)))
            except (AttributeError, TypeError, ValueError):
                raise InputError(
                    f"sensors(): camera {name} has no usable width/height ({c!r})"
                ) from None
        stereo = {n: s for n, s in sizes.items() if any(n in p for p in STEREO_PAIRS)}
        if not stereo:
            raise InputError(
                "sensors(): no active stereo camera "
                f"({', '.join(n for p in STEREO_PAIRS for n in p)}); active: "
                f"{', '.join(sizes) or 'none'}"
            )
        if len(set(stereo.values())) > 1:
            raise InputError(
                f"sensors(): stereo cameras differ in size {stereo}; one intrinsic model is "
                "supported"
            )
        w, h = next(iter(stereo.values()))
        cam = PinholeCamera(w, h, hfov_deg)
        poses = {n: m.T_rover_cam for n, m in ipex_rig(cam).items()}
        for key, p in dict(camera_poses or {}).items():
            T = as_transform_matrix(p, f"pose of camera {camera_name(key)}")
            if np.allclose(T, np.eye(4)):
                # a zero pose (PlaybackAgent before the camera's first row): keep the rig's
                continue
            poses[camera_name(key)] = T
        return cls(cam, poses)

    @classmethod
    def from_calibration(
        cls,
        width: int,
        height: int,
        fx: float,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        baseline_m: float = IPEX_STEREO_BASELINE_M,
        T_rover_cam: Mapping | None = None,
    ) -> CameraRig:
        """From one's own calibration: pixels ``fx, fy, cx, cy``, the stereo ``baseline_m`` (the
        IPEx rig's layout with that baseline) or explicit ``T_rover_cam`` poses. The camera
        model is a centred square-pixel pinhole: ``fy`` must equal ``fx`` and ``(cx, cy)`` be the
        image centre within a pixel (rectify the images first otherwise)."""
        width = validate.integer(width, "calibration width", 16, 8192)
        height = validate.integer(height, "calibration height", 16, 8192)
        fx = validate.real(fx, "calibration fx", 0.0, lo_open=True)
        fy = fx if fy is None else fy
        cx = (width - 1) / 2 if cx is None else cx
        cy = (height - 1) / 2 if cy is None else cy
        if not (fx > 0 and width > 0 and height > 0):
            raise InputError(f"calibration: fx={fx}, width={width}, height={height} must be > 0")
        if (
            abs(fy - fx) > 1e-3 * fx
            or abs(cx - (width - 1) / 2) > 1.0
            or abs(cy - (height - 1) / 2) > 1.0
        ):
            raise InputError(
                f"calibration: fx={fx}, fy={fy}, cx={cx}, cy={cy}: the camera model needs fy == fx "
                f"and the principal point at the image centre ({(width - 1) / 2}, "
                f"{(height - 1) / 2}); rectify first"
            )
        cam = PinholeCamera(int(width), int(height), math.degrees(2 * math.atan(width / 2 / fx)))
        if T_rover_cam is None:
            if not baseline_m > 0:
                raise InputError(f"calibration: baseline_m={baseline_m} must be > 0")
            rig = ipex_rig(cam)
            T_rover_cam = {}
            for n, m in rig.items():
                T = m.T_rover_cam.copy()
                T[1, 3] = math.copysign(baseline_m / 2, T[1, 3])
                T_rover_cam[n] = T
        return cls(cam, T_rover_cam)

    def mounts(self) -> dict[str, CameraMount]:
        return {n: CameraMount(n, T, self.camera) for n, T in self.T_rover_cam.items()}

    @classmethod
    def lac(cls, width: int = 1280, height: int = 720) -> CameraRig:
        """The LAC's IPEx cameras (fixed 70 degree pinholes, the known mounts) at a resolution."""
        cam = PinholeCamera(int(width), int(height), 70.0)
        return cls(cam, {n: m.T_rover_cam for n, m in ipex_rig(cam).items()})

    def same_mounts(self, other: CameraRig, tol_m: float = 1e-3, tol_rad: float = 1e-3) -> bool:
        """Same intrinsics and, for the cameras both hold, the same poses within the tolerances."""
        if self.camera != other.camera:
            return False
        for n in set(self.T_rover_cam) & set(other.T_rover_cam):
            A, B = self.T_rover_cam[n], other.T_rover_cam[n]
            if (
                np.abs(A[:3, 3] - B[:3, 3]).max() > tol_m
                or np.abs(A[:3, :3] - B[:3, :3]).max() > tol_rad
            ):
                return False
        return True


@dataclass(frozen=True)
class OnlineConfig:
    """Settings of the component (metres, seconds, degrees as named)."""

    loop: LoopConfig = field(default_factory=image_loop_config)
    localization: LocalizationConfig = field(default_factory=image_localization_config)
    imu: ImuOdometryConfig = field(default_factory=ImuOdometryConfig)
    visual_odometry: bool = (
        True  # stereo VO on image ticks (else IMU only) when no odometry is passed
    )
    keyframe_min_travel_m: float = 0.05  # an image tick is a keyframe after this much travel ...
    keyframe_min_turn_deg: float = 2.0  # ... or this much turning ...
    keyframe_max_interval_s: float = 2.0  # ... or this long since the last keyframe
    max_keyframes: int = 1500  # re-anchor the pose graph when it holds this many keyframes
    reference_max_distance_m: float = (
        50.0  # the reference must have a landmark this close to the initial pose
    )
    initial_sigma_m: float = 0.05  # uncertainty of the initial pose (position) ...
    initial_sigma_yaw_deg: float = 0.5  # ... and heading
    tilt_sigma_deg: float = 0.5  # roll / pitch sigma reported in the covariance (gravity-levelled)
    max_recent_attempts: int = 100  # localization attempts kept in `recent_attempts`
    # where the stated covariance restarts at an accepted fix: "graph", the pose graph's marginal
    # covariance of the estimate it reports; "fix", the covariance stated for the fix itself
    covariance_source: str = "graph"

    def __post_init__(self) -> None:
        if self.covariance_source not in ("graph", "fix"):
            raise ConfigError(
                f"covariance_source={self.covariance_source!r}: use one of graph, fix"
            )
        # 10**9: never re-anchor
        validate.integer(self.max_keyframes, "max_keyframes", 50, 10**9, ConfigError)
        validate.integer(self.max_recent_attempts, "max_recent_attempts", 0, 10**6, ConfigError)
        for name in (
            "keyframe_min_travel_m",
            "keyframe_min_turn_deg",
            "keyframe_max_interval_s",
            "reference_max_distance_m",
            "initial_sigma_m",
            "initial_sigma_yaw_deg",
            "tilt_sigma_deg",
        ):
            validate.real(getattr(self, name), name, 0.0, lo_open=True, error=ConfigError)
        for name, cls in (
            ("loop", LoopConfig),
            ("localization", LocalizationConfig),
            ("imu", ImuOdometryConfig),
            ("visual_odometry", bool),
        ):
            validate.instance(getattr(self, name), name, cls)

    def to_dict(self) -> dict:
        from lunarloc.core.configs import config_to_dict

        return config_to_dict(self)


@dataclass(frozen=True)
class Estimate:
    """The rover pose at one tick. ``covariance`` is 6x6 over (x, y, z, roll, pitch, yaw) in
    m^2 / rad^2: the pose graph's marginal covariance of its estimate at the last accepted fix
    (``OnlineConfig.covariance_source``), grown by the odometry's drift bounds over the path
    since. ``localized``: a fix from the reference map has been accepted at some tick."""

    mission_time_s: float
    T_map_rover: np.ndarray
    covariance: np.ndarray
    localized: bool
    fixes: int = 0  # accepted fixes so far
    keyframe: bool = False  # this tick was a keyframe (detector ran)
    attempt: Attempt | None = None  # the localization attempt made at this tick, if any


# --------------------------------------------------------------------------- the component


class OnlineLocalizer:
    """Per-tick global localization against a reference rock map (see the module docstring).

    reference : the reference map (frame ``map``), e.g. :func:`lunarloc.load_reference`; None
        for a rover with no reference (its attempts end "no reference map"; a caller such as
        :mod:`lunarloc.pipeline.multirover` localizes their local maps in other rovers' maps).
        ``localized`` then stays False.
    initial_pose : the rover's pose in ``map`` at the first tick (the LAC's
        ``get_initial_position()``: the leaderboard's right-handed Transform, a 4x4 or
        (x, y, z, roll, pitch, yaw); see :func:`as_transform_matrix`).
    config : :class:`OnlineConfig`.
    rig : :class:`CameraRig` (intrinsics and mounts), e.g. :meth:`CameraRig.from_sensors` /
        :meth:`CameraRig.from_calibration`; default the LAC's IPEx rig (fixed 70 degree
        pinholes) at the resolution of the first images delivered (1280x720 until then).
    detector_config : default :func:`lunarloc.config.run.scaled_detector_config` at the rig's width.
    lander_pose : the lander's pose relative to the rover at the first tick (the LAC's
        ``get_initial_lander_position()``, in any form `initial_pose` takes); detections on
        the lander are then dropped. None: no lander exclusion.
    mapper : optional :class:`~lunarloc.mapping.lac_map.LacMapper`: every keyframe's stereo
        points and detections are added to it with the tick's estimate (frame id: the tick
        number), and after each accepted fix the keyframes still in the pose graph are
        re-placed with their corrected poses; ``mapper.grid()`` is the LAC map so far.
    """

    def __init__(
        self,
        reference: LandmarkMap | None,
        initial_pose,
        config: OnlineConfig | None = None,
        rig: CameraRig | None = None,
        detector_config=None,
        lander_pose=None,
        mapper=None,
    ):
        from lunarloc.perception.detector import DetectorConfig

        if config is not None:  # the types first: a string here was an AttributeError deep inside
            validate.instance(config, "config", OnlineConfig, "lunarloc.OnlineConfig")
        if detector_config is not None:
            validate.instance(
                detector_config,
                "detector_config",
                DetectorConfig,
                "lunarloc.perception.detector.DetectorConfig",
            )
        if reference is not None and not isinstance(reference, LandmarkMap):
            raise InputError(
                f"reference must be a LandmarkMap (see lunarloc.load_reference) or None, "
                f"got {type(reference).__name__}"
            )
        self.config = cfg = config or OnlineConfig()
        self.rig = rig or CameraRig()
        if not isinstance(self.rig, CameraRig):
            raise InputError(f"rig must be a CameraRig, got {type(self.rig).__name__}")
        self.T_map_rover0 = as_transform_matrix(initial_pose, "initial_pose")
        # the lander's centre in map (= odometry at the start), for dropping detections on it
        self._lander_xy = (
            None
            if lander_pose is None
            else (self.T_map_rover0 @ as_transform_matrix(lander_pose, "lander_pose"))[:2, 3]
        )
        self.reference = reference
        if reference is not None and len(reference) >= 1:
            d = np.linalg.norm(reference.positions_xyz[:, :2] - self.T_map_rover0[:2, 3], axis=1)
            if float(d.min()) > cfg.reference_max_distance_m:
                raise InputError(
                    f"the reference map has no landmark within {cfg.reference_max_distance_m:g} m "
                    f"of the initial pose ({float(d.min()):.1f} m to the nearest): is it in "
                    "another frame than the initial pose?"
                )
        noise = replace(
            cfg.loop.fusion.noise,
            start_sigma_m=cfg.initial_sigma_m,
            start_sigma_yaw_rad=math.radians(cfg.initial_sigma_yaw_deg),
        )
        self._loop_config = replace(cfg.loop, fusion=replace(cfg.loop.fusion, noise=noise))
        # its windows state the bounds of the odometry that places them (LoopConfig.window_bounds)
        self._odometry_source = "visual" if cfg.visual_odometry else "imu"
        # checks the reference (>= 3 landmarks)
        self.loop = LoopState(
            reference, self._loop_config, cfg.localization, odometry=self._odometry_source
        )
        self._rig_given = rig is not None  # else the LAC rig, sized to the first images delivered
        self._detector_config = detector_config
        self._use_rig(self.rig)
        # per-tick state (constant size)
        self._tick = 0
        self._t_prev: float | None = None
        self._imu_prev: np.ndarray | None = None
        self._speed_prev = 0.0
        self._T_map_imu = self.T_map_rover0.copy()  # IMU dead reckoning
        # odometry (visual / IMU / caller), odo == map at start
        self._T_map_odo = self.T_map_rover0.copy()
        self._vo_anchor = None  # (T_map_odo at the last VO pair, T_map_imu there)
        # the visual steps' stated variance since the last keyframe (m^2; None: a step without
        # one), read only where the pose graph uses it (OdometryNoise.measured_step_scale)
        self._step_var: float | None = 0.0
        self._T_odo_caller = None  # T_odo_caller: the caller's odometry frame in ours
        self._T_loop_odo = np.eye(4)  # the loop's odometry frame <- odo (changes at re-anchors)
        self._last_kf = None  # (t, T_odo_rover) of the last keyframe
        self._fixes = 0
        # the stated covariance (_covariance): propagated from an anchor (the start, then the last
        # accepted fix: its position covariance and yaw variance) by the odometry's drift over the
        # path travelled since (_path_m: odometry path length, m)
        self._path_m = 0.0
        self._sigmas = (cfg.initial_sigma_m, math.radians(cfg.initial_sigma_yaw_deg))
        self._anchor = CovarianceAnchor(
            np.eye(3) * cfg.initial_sigma_m**2,
            math.radians(cfg.initial_sigma_yaw_deg) ** 2,
            0.0,
            self.T_map_rover0[:3, 3].copy(),
        )
        self.reanchors = 0
        self.recent_attempts: collections.deque[Attempt] = collections.deque(
            maxlen=cfg.max_recent_attempts
        )
        self.mapper = mapper  # the LAC map: fed at keyframes, see _feed_mapper
        self._fd = None  # the last keyframe's detector output (for the mapper)
        if mapper is not None and self._lander_xy is not None:
            from lunarloc.mapping.lac_map import LANDER_EXCLUSION_M

            mapper.exclude_disc(self._lander_xy, LANDER_EXCLUSION_M)
        # the pose returned at every tick (t, then the top 3x4 of T_map_rover): 104 bytes a tick,
        # 15 MB for a 2 h mission at 20 Hz; read with trajectory(), saved with write_trajectory()
        self._history = array.array("d")

    def _use_rig(self, rig: CameraRig) -> None:
        """Detector, mounts, stereo pairs and visual odometry for `rig`."""
        from lunarloc.perception.detector import Detector, scaled_detector_config

        self.rig = rig
        self.detector = Detector(
            self._detector_config or scaled_detector_config(rig.camera.width), rig.camera
        )
        self._mounts = rig.mounts()
        self._pairs = [
            p for p in self.detector.config.pairs if p[0] in self._mounts and p[1] in self._mounts
        ]
        self._vo = None
        if self.config.visual_odometry:
            left, right = STEREO_PAIRS[0]
            if left in self._mounts and right in self._mounts:
                from lunarloc.odometry.tilt import GravityAlignedChain
                from lunarloc.odometry.visual import StereoVisualOdometry

                self._vo = StereoVisualOdometry(
                    rig.camera,
                    self._mounts[left].T_rover_optical,
                    self._mounts[right].T_rover_optical,
                )
                # roll/pitch from gravity
                self._vo_chain = GravityAlignedChain(self._vo.config.gravity_tilt_gain)

    # -------------------------------------------------------------- public
    def warm_up(self) -> float:
        """Compile the association kernels, import and run the pose graph, the local-map
        aggregation, the detector and the visual odometry once on synthetic data, so that the
        first ticks of the mission pay no one-off cost (imports, compilation). Returns the
        seconds taken."""
        import time

        from lunarloc.localization.warmup import warm_up

        t0 = time.perf_counter()
        warm_up()
        # the pose graph's first gate and solve import scipy.stats / scipy.optimize (~1 s)
        from lunarloc.fusion.posegraph import PoseGraph

        g = PoseGraph(self._loop_config.fusion)
        for i in range(3):
            g.add_keyframe(float(i), (0.1 * i, 0.0, 0.0, 0.0))
        g.gate(2, (0.2, 0.0, 0.0, 0.0), 0.05, 0.01)
        g.add_fix(2, (0.2, 0.01, 0.0, 0.0), 0.05, 0.01)
        g.solve()
        # ... and the local map's first aggregation imports scikit-learn (DBSCAN)
        from lunarloc.io.maps import aggregate_detections

        pts = np.random.default_rng(0).uniform(-3, 3, (20, 3))
        aggregate_detections(
            np.r_[pts, pts + 0.01], np.repeat([0, 1], 20), self._loop_config.aggregation
        )
        c = self.rig.camera
        blank = np.zeros((c.height, c.width), np.uint8)
        blank[c.height // 2 :] = 90
        images = {n: blank for p in self._pairs[:1] for n in p}
        if images:
            self.detector.detect_frame(images, self._mounts)
        if self._vo is not None:
            from lunarloc.odometry.visual import StereoVisualOdometry

            left, right = STEREO_PAIRS[0]
            vo = StereoVisualOdometry(
                self.rig.camera,
                self._mounts[left].T_rover_optical,
                self._mounts[right].T_rover_optical,
            )
            vo.update(blank, blank)
            vo.update(blank, blank)
        return time.perf_counter() - t0

    @property
    def localized(self) -> bool:
        return self._fixes > 0

    def set_caller_odometry(self, source) -> None:
        """Say which odometry the caller passes to :meth:`update` as ``odometry=``: a source
        label (``visual``, ``record:NAME``, ``imu``, as
        :attr:`lunarloc.odometry.source.OdometryTrajectory.label` writes it) or its
        :class:`~lunarloc.online.loop.OdometryBounds`, so that the local windows state that
        odometry's distortion bounds (``LoopConfig.window_bounds = "source"``), as ``lunarloc
        run`` does for the same source. Without it the caller's odometry is of unknown
        accuracy and each window's bend is fitted from its inliers. Call before the first
        :meth:`update`; None goes back to unknown."""
        if source is not None and not isinstance(source, (str, OdometryBounds)):
            raise InputError(
                "source must be an odometry source label or OdometryBounds, got "
                f"{type(source).__name__}"
            )
        self._odometry_source = None  # update() keeps what the caller stated
        self.loop.set_odometry(source)

    def update(
        self,
        mission_time_s: float,
        input_data: Mapping | None,
        imu,
        linear_speed: float,
        angular_speed: float,
        odometry=None,
    ) -> Estimate:
        """One tick: the LAC's ``input_data`` as the leaderboard hands it (``{"Grayscale":
        {camera: (H, W) uint8 image or None}, "Semantic": {...}}``; camera keys
        ``SensorPosition`` members or names; views are fine; the semantic group is not used),
        ``get_imu_data()`` (6,: body-frame specific force, world-frame angular rate, as the
        leaderboard computes them; see :attr:`ImuOdometryConfig.gyro_frame`),
        ``get_linear_speed()`` (m/s), ``get_angular_speed()`` (rad/s) and optionally the
        caller's odometry ``T_odo_rover`` (4x4, 6-vector or Transform, any fixed frame).
        Raises InputError on malformed input (the component's state is then unchanged)."""
        t = self._check_time(mission_time_s)
        a = self._check_imu(imu, linear_speed, angular_speed)
        linear_speed = float(linear_speed)
        images = self._images(input_data)
        T_caller = None if odometry is None else as_transform_matrix(odometry, "odometry")
        pair = self._stereo_pair(images)  # may refuse: before any state changes
        if T_caller is not None and self._odometry_source is not None:
            self._odometry_source = (
                None  # the caller's odometry: its bounds are not known, its windows' bend is fitted
            )
            self.loop.set_odometry(None)
        # ---- odometry
        if self._t_prev is None:
            T_imu = self._T_map_imu
        else:
            s = ImuSamples(
                np.arange(2),
                np.array([self._t_prev, t]),
                np.stack([self._imu_prev[:3], a[:3]]),
                np.stack([self._imu_prev[3:], a[3:]]),
                np.array([self._speed_prev, float(linear_speed)]),
            )
            T_imu = integrate_imu(s, self._T_map_imu, self.config.imu)[1]
        visual = (  # this tick is a visual odometry step
            T_caller is None
            and self._vo is not None
            and pair is not None
            and pair[0] == STEREO_PAIRS[0][0]
        )
        if T_caller is not None:
            if self._T_odo_caller is None:
                self._T_odo_caller = self._T_map_odo @ invert_transform(T_caller)
            T_odo = self._T_odo_caller @ T_caller
        elif visual:
            T_odo = self._visual(images, T_imu)
        elif self._vo_anchor is not None:  # bridge with the IMU since the last VO pair
            T_odo_vo, T_imu_vo = self._vo_anchor
            T_odo = T_odo_vo @ invert_transform(T_imu_vo) @ T_imu
        else:
            T_odo = T_imu
        self._t_prev, self._imu_prev, self._speed_prev = t, a, float(linear_speed)
        self._path_m += float(np.linalg.norm(T_odo[:3, 3] - self._T_map_odo[:3, 3]))
        self._T_map_imu, self._T_map_odo = T_imu, T_odo
        self._tick += 1
        # ---- keyframe: detection, localization, fusion
        attempt, is_kf = None, False
        if pair is not None and self._is_keyframe(t, T_odo):
            is_kf = True
            det = self._detect(images)
            if self._lander_xy is not None:
                from lunarloc.perception.detector import on_lander

                det = det[~on_lander(det, T_odo, self._lander_xy)]
            if len(self.loop.keyframes) >= self.config.max_keyframes:
                self._reanchor()
            stated = (  # the visual steps' own sigma, where the pose graph uses it
                visual
                and self._step_var is not None
                and self.loop.config.fusion.noise.measured_step_scale is not None
            )
            attempt = self.loop.step(
                self._tick,
                t,
                self._T_loop_odo @ T_odo,
                det,
                None,
                keyframe=True,
                odometry_step_sigma_m=math.sqrt(self._step_var) if stated else None,
            )
            self._step_var = 0.0
            self._last_kf = (t, T_odo)
            self._sigmas = self.loop.graph.predicted_sigma(len(self.loop.keyframes) - 1)
            if attempt is not None:
                self.recent_attempts.append(attempt)
                self._fixes += int(attempt.accepted)
        T = self.loop.T_map_odo @ self._T_loop_odo @ T_odo
        if attempt is not None and attempt.accepted and attempt.fix_covariance_xyz is not None:
            self._anchor = self._fix_anchor(attempt, T)
        if is_kf and self.mapper is not None:
            self._feed_mapper(images, T, attempt)
        self._history.append(t)
        self._history.extend(T[:3, :].reshape(-1))
        return Estimate(t, T, self._covariance(T), self.localized, self._fixes, is_kf, attempt)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Every pose :meth:`update` returned so far: (times (F,) s, T_map_rover (F, 4, 4)).
        These are the causal (online) poses, what the rover knew at each tick; a later fix
        does not rewrite them."""
        h = np.frombuffer(self._history, dtype=float).reshape(-1, 13).copy()
        T = np.tile(np.eye(4), (len(h), 1, 1))
        T[:, :3, :] = h[:, 1:].reshape(-1, 3, 4)
        return h[:, 0], T

    def write_trajectory(self, path, format: str = "tum"):
        """Write :meth:`trajectory` to `path` as ``"tum"`` (t x y z qx qy qz qw, what evo reads)
        or ``"kitti"`` (12 numbers a line, no times); atomically. Returns the path."""
        from lunarloc.io.trajectory import write_kitti, write_tum

        times, T = self.trajectory()
        if format == "tum":
            return write_tum(path, times, T)
        if format == "kitti":
            return write_kitti(path, T)
        raise InputError(f"trajectory format must be 'tum' or 'kitti'; got {format!r}")

    # -------------------------------------------------------------- checks
    def _check_time(self, mission_time_s) -> float:
        t = validate.real(mission_time_s, "mission_time_s", unit="s")
        if self._t_prev is None or t > self._t_prev:
            validate.real(t, "mission_time_s", 0.0, validate.MAX_MISSION_TIME_S, unit="s")
        if self._t_prev is not None:
            if t <= self._t_prev:
                raise InputError(
                    f"mission_time_s went backwards or stood still: {t:.3f} s after "
                    f"{self._t_prev:.3f} s"
                )
            if t - self._t_prev > self.config.imu.max_dt_s:
                raise InputError(
                    f"{t - self._t_prev:.3f} s since the previous tick (max "
                    f"{self.config.imu.max_dt_s:g} s): call update() every tick"
                )
        return t

    @staticmethod
    def _check_imu(imu, linear_speed, angular_speed) -> np.ndarray:
        """The IMU sample and speeds within physical bounds (lunarloc.core.validate)."""
        a = validate.imu_sample(imu, "imu")
        m = validate.MAX_LINEAR_SPEED_MPS
        validate.real(linear_speed, "linear_speed", -m, m, unit="m/s")
        m = validate.MAX_ANGULAR_SPEED_RADPS
        validate.real(angular_speed, "angular_speed", -m, m, unit="rad/s")
        return a

    def _images(self, input_data) -> dict[str, np.ndarray | None]:
        """{camera name: image or None} of the Grayscale group; shapes checked."""
        if input_data is None:
            return {}
        if not isinstance(input_data, Mapping):
            raise InputError(
                f"input_data must be a dict like {{'Grayscale': {{camera: image}}}}, got "
                f"{type(input_data).__name__}"
            )
        group = input_data.get("Grayscale")
        group = {} if group is None else group
        if not isinstance(group, Mapping):
            raise InputError(
                f"input_data['Grayscale'] must be a dict {{camera: image or None}}, got "
                f"{type(group).__name__}"
            )
        names = {camera_name(k) for k in group}
        if names and not any(n in names for p in self._pairs for n in p):
            raise InputError(
                f"input_data['Grayscale'] has no stereo camera (has {', '.join(sorted(names))}); "
                "the component needs one of the pairs "
                f"{', '.join('/'.join(p) for p in self._pairs)} active"
            )
        # arrays only
        first = next((getattr(im, "shape", None) for im in group.values() if im is not None), None)
        if (
            isinstance(first, tuple)
            and len(first) == 2
            and 0 < first[0] <= 2048
            and 0 < first[1] <= 2448
            and not self._rig_given
            and self._last_kf is None
            and self._vo_anchor is None
            and first != (self.rig.camera.height, self.rig.camera.width)
        ):
            # the LAC's cameras are fixed pinholes: the intrinsics follow from the size
            h, w = (int(v) for v in first)
            log.info("no rig given: the LAC rig at the delivered %dx%d", w, h)
            self._use_rig(CameraRig.lac(w, h))
        c = self.rig.camera
        out = {}
        for key, img in group.items():
            name = camera_name(key)
            if img is not None:
                img = validate.gray_image(
                    img, f"input_data['Grayscale'][{name}]", (c.height, c.width)
                )
                # the leaderboard hands a view ([:, :, 0] of a BGRA buffer)
                img = np.ascontiguousarray(img)
            out[name] = img
        return out

    def _stereo_pair(self, images: dict) -> tuple[str, str] | None:
        """The first configured pair with both images at this tick; InputError when one of a
        pair has an image and the other none."""
        found = None
        for left, right in self._pairs:
            has_l, has_r = images.get(left) is not None, images.get(right) is not None
            if has_l != has_r:
                missing = right if has_l else left
                raise InputError(
                    f"input_data: {left if has_l else right} has an image but {missing} "
                    f"{'is missing' if missing not in images else 'is None'}: a stereo pair is "
                    "captured together"
                )
            if has_l and found is None:
                found = (left, right)
        return found

    # -------------------------------------------------------------- steps
    def _visual(self, images: dict, T_imu: np.ndarray) -> np.ndarray:
        left, right = STEREO_PAIRS[0]
        prior = None
        if self._vo_anchor is not None:
            prior = invert_transform(self._vo_anchor[1]) @ T_imu
        T_vo_rover = self._vo.update(images[left], images[right], prior)
        if self.loop.config.fusion.noise.measured_step_scale is not None:
            C = self._vo.last_step_covariance  # computed when read: only where it is used
            if C is None or self._step_var is None:  # a step the odometry states no sigma for
                self._step_var = None
            else:
                self._step_var += max(float(np.linalg.eigvalsh(C[:3, :3])[-1]), 0.0)
        # visual motion chained from the first pair's predicted pose, roll and pitch from the IMU's
        # gravity
        T_odo = self._vo_chain.add(T_vo_rover, T_imu, self._T_map_odo_prediction(T_imu))
        self._vo_anchor = (T_odo, T_imu)
        return T_odo

    def _T_map_odo_prediction(self, T_imu: np.ndarray) -> np.ndarray:
        """The odometry pose this tick would have without vision (IMU since the last tick)."""
        return self._T_map_odo @ invert_transform(self._T_map_imu) @ T_imu

    def _is_keyframe(self, t: float, T_odo: np.ndarray) -> bool:
        if self._last_kf is None:
            return True
        t_kf, T_kf = self._last_kf
        c = self.config
        rel = invert_transform(T_kf) @ T_odo
        turn = math.degrees(abs(math.atan2(rel[1, 0], rel[0, 0])))
        return (
            np.linalg.norm(rel[:3, 3]) >= c.keyframe_min_travel_m
            or turn >= c.keyframe_min_turn_deg
            or t - t_kf >= c.keyframe_max_interval_s
        )

    def _detect(self, images: dict) -> np.ndarray:
        imgs = {
            n: im for n, im in images.items() if im is not None and any(n in p for p in self._pairs)
        }
        fd = self.detector.detect_frame(
            imgs, self._mounts, None, self._tick, keep_depth=self.mapper is not None
        )
        self._fd = fd if self.mapper is not None else None
        return np.array([d.p_rover for d in fd.detections], float).reshape(-1, 3)

    def _drift_bounds(self) -> OdometryBounds | None:
        """The odometry's drift per metre (scale error, heading drift) the covariance grows
        with: the bounds of the source that feeds the loop (:attr:`LoopConfig.odometry_bounds`);
        None where none are known (IMU only, a caller's own odometry)."""
        src = self.loop.odometry
        if isinstance(src, OdometryBounds):
            return src
        if isinstance(src, str):
            return self._loop_config.odometry_bounds.for_source(src)
        return None

    def _covariance(self, T_map_rover: np.ndarray) -> np.ndarray:
        """6x6 over (x, y, z, roll, pitch, yaw). Once localized: propagated from the last
        accepted fix (the pose graph's marginal covariance of its estimate there,
        :meth:`_fix_anchor`) by
        :func:`propagate_covariance` over the odometry path since, with the odometry source's
        drift bounds. Before the first fix: the pose graph's gate model at the newest keyframe
        (the odometry is not calibrated yet, and its first metres can jump beyond its bounds:
        docs/calibration.md, "The online loop's uncertainty"). Roll and pitch:
        ``tilt_sigma_deg``."""
        st = math.radians(self.config.tilt_sigma_deg)
        C = np.zeros((6, 6))
        C[3, 3] = C[4, 4] = st**2
        if not self.localized:
            sm, sy = self._sigmas
            C[0, 0] = C[1, 1] = C[2, 2] = sm**2
            C[5, 5] = sy**2
            return C
        b = self._drift_bounds()
        if b is None:  # no drift known: the gate's rates (an odometry of unknown grade)
            g = self._loop_config.fusion.gate
            b = OdometryBounds(g.rate_m_per_m, g.yaw_rate_deg_per_m)
        P, yaw_var = propagate_covariance(self._anchor, self._path_m, b, T_map_rover[:3, 3])
        C[:3, :3] = P
        C[5, 5] = yaw_var
        return C

    def _fix_anchor(self, attempt, T_map_rover: np.ndarray) -> CovarianceAnchor:
        """Where the stated covariance restarts after an accepted fix: the pose graph's marginal
        covariance of its newest keyframe (this tick's, whose estimate is ``T_map_rover``) under
        its noise model plus the vertical part of the centre bias the fix's window of rocks
        shares (:func:`window_centre_bias_covariance`: detected centres sit on the rocks' tops
        from every side, so the vertical bias does not average out over the many headings of
        the graph's active window as the horizontal one does), when the fix's solve gave one
        (``covariance_source = "graph"``); else the covariance the loop states for the fix at
        the rover. The graph's estimate is not the fix (docs/calibration.md, "(b)
        OnlineLocalizer along image-built runs")."""
        graph = self.config.covariance_source == "graph"
        C = self.loop.graph.newest_covariance if graph else None  # a sparse solve: only if used
        if C is not None:
            B = window_centre_bias_covariance(attempt.fix_maps_from_detections, self._loop_config)
            xyz, yaw_var = C[:3, :3] + np.diag([0.0, 0.0, B[2, 2]]), C[3, 3]
        else:
            xyz, yaw_var = attempt.fix_covariance_xyz, attempt.fix_sigma_yaw_rad**2
        return CovarianceAnchor(
            np.array(xyz, float), float(yaw_var), self._path_m, T_map_rover[:3, 3].copy()
        )

    def _reanchor(self) -> None:
        """Start a new loop state from the keyframes of the last window (bounded history)."""
        old = self.loop
        cfg = self._loop_config
        n = len(old.keyframes)
        keep = old.window(n - 1)[-self.config.max_keyframes // 3 :]
        poses = old.graph.poses()
        sm, sy = old.graph.predicted_sigma(int(keep[0]))
        noise = replace(
            cfg.fusion.noise,
            start_sigma_m=max(sm, cfg.fusion.noise.start_sigma_m),
            start_sigma_yaw_rad=max(sy, cfg.fusion.noise.start_sigma_yaw_rad),
        )
        new = LoopState(
            self.reference,
            replace(cfg, fusion=replace(cfg.fusion, noise=noise)),
            self.config.localization,
            odometry=old.odometry,
        )
        # no attempts while the window is re-fed
        new._last_attempt_dist = new._last_attempt_t = math.inf
        for k in keep:
            kf = old.keyframes[k]
            x, y, z, yaw = poses[k]
            roll, pitch = kf.roll_pitch_rad
            new.step(
                kf.frame,
                kf.t_s,
                pose_to_matrix(x, y, z, roll, pitch, yaw),
                kf.detections_rover,
                None,
                keyframe=True,
                odometry_step_sigma_m=kf.step_sigma_m,
            )
        g_old, g_new = old.graph, new.graph
        # the gate's drift model continues from the last fix (distance and time since it)
        g_new._last_fix_dist = g_new.keyframes[-1].distance_m - (
            g_old.keyframes[-1].distance_m - g_old._last_fix_dist
        )
        g_new._last_fix_time = g_old._last_fix_time
        new._last_attempt_dist = new._dist - (old._dist - old._last_attempt_dist)
        new._last_attempt_t = old._last_attempt_t
        # the new loop's odometry frame is the map estimate at the last kept keyframe
        self._T_loop_odo = old._correction(n - 1) @ self._T_loop_odo
        self.loop = new
        self.reanchors += 1
        log.debug("re-anchored the pose graph: %d keyframes -> %d", n, len(keep))

    # -------------------------------------------------------------- the LAC map
    def _feed_mapper(self, images: dict, T_map_rover: np.ndarray, attempt) -> None:
        """Add this keyframe to the mapper at the tick's estimate; after an accepted fix,
        re-place the keyframes the pose graph still holds with their corrected poses."""
        from lunarloc.mapping.lac_map import frame_inputs

        if self._fd is not None:
            points, rocks = frame_inputs(self._fd, self.detector, images)
            self.mapper.add_frame(self._tick, T_map_rover, points, rocks)
            self._fd = None
        if attempt is not None and attempt.accepted:
            for kf in self.loop.keyframes:
                if kf.frame is None:
                    continue
                x, y, z, yaw = (float(v) for v in kf.estimate_pose4)
                roll, pitch = kf.roll_pitch_rad
                self.mapper.repose(kf.frame, pose_to_matrix(x, y, z, roll, pitch, yaw))
