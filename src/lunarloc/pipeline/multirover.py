"""Several rovers on one clock: archives played in mission-time order, each rover localizing
against a reference map and/or the other rovers' live maps (LunarLoc's multi-agent playback).

``run_rovers([a.lac, b.lac], reference=None, config=MultiRoverConfig(share_maps=True))``
(every rover runs with ``config.run``, the :class:`~lunarloc.config.run.RunConfig` of ``lunarloc run``):

1. **one clock**: every archive is a :class:`~lunarloc.io.lac.playback.PlaybackAgent`; at each
   step the rover whose next tick is earliest in mission time is played (ties: argument order);
2. **per rover**: one :class:`~lunarloc.online.component.OnlineLocalizer` per rover, fed tick by tick
   with its odometry (:func:`lunarloc.odometry.source.archive_odometry`, the source ``lunarloc run``
   uses) and its images; its reference attempts, gate and fixes are the single-rover ones;
3. **shared maps** (``share_maps``): when a rover's localization attempt at a keyframe did
   not give an accepted fix, its local map (the same window the reference attempt used) is
   localized in each other rover's *live map*, the rock landmarks that rover has placed so
   far with its current pose estimates, by :func:`lunarloc.localization.localize.localize` with the
   same checks as a reference fix and what differs stated in its configuration
   (:func:`shared_localization`: both maps' odometry bounds, precision no finer than the maps),
   then gated like any fix;
4. **outputs**: one :class:`~lunarloc.online.loop.LoopResult` per rover (the run folder of
   ``lunarloc run``, its ``config.json`` the RunConfig plus an ``info`` section) plus the
   shared attempts.

Frames: every LAC rover knows its initial pose in the site (``get_initial_position()``), so
all rovers share the ``map`` frame up to their odometry drift; a rover's live map is in its
own estimate of ``map``.

Uncertainty of a shared map. A landmark of another rover (the *owner*) is off by the
owner's pose error at the keyframes that saw it: mostly a rigid offset common to the
landmarks of one neighbourhood (the owner's drift varies slowly), not independent noise.
Treating it as per-landmark noise would be wrong both ways: it would loosen the
association's tolerances (which only need the map's *relative* geometry), and the fitted
pose would average it down by sqrt(inliers) into false confidence. So the shared map keeps
each landmark's own sighting sigma for the association, and records per landmark the
owner's absolute sigma (position, yaw) there; an accepted registration becomes a pose fix
whose sigmas are the registration's own combined in quadrature with the largest owner sigma
among its inliers. The owner's sigma is its odometry's stated bounds since its last fix, per
window (:meth:`_Rover.sigma`; at most the gate's drift model,
:meth:`lunarloc.fusion.posegraph.PoseGraph.predicted_sigma`), combined with the sigma of that fix
when it was itself a shared fix (a rover aligned to another inherits that rover's error). A
shared fix is used only when it is clearly more certain than the rover's own prediction.
"""

from __future__ import annotations

import heapq
import logging
import math
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lunarloc.config.run import RunConfig, config_from_dict, config_to_dict
from lunarloc.core.errors import ConfigError, InputError, LunarLocError
from lunarloc.core.geometry import invert_transform, pose_to_matrix, yaw_of
from lunarloc.online.loop import Attempt, LoopResult, interpolate_corrections, stated_window_bounds
from lunarloc.io.maps import LandmarkMap, aggregate_detections

if TYPE_CHECKING:
    from lunarloc.localization.config import LocalizationConfig

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "MultiRoverConfig",
    "SharedAttempt",
    "RoverRun",
    "MultiRoverResult",
    "check_archives",
    "rover_names",
    "run_rovers",
    "write_rover_outputs",
]


SHARED_BOUNDS = ("sum", "rss", "own")


def shared_localization(
    window: LocalizationConfig,
    owner_bounds: tuple[float, float] | None,
    how: str = "sum",
    owner_sigma: tuple[float, float] | None = None,
) -> LocalizationConfig:
    """The localization a rover's local window is judged with in another rover's live map.

    :func:`~lunarloc.localization.localize.localize` takes its reference as rigid and allows
    for the vehicle map's bend from the odometry bounds the configuration states. A live map is
    not rigid: the owner placed its landmarks with its own drifting odometry (corrected by its
    pose graph). Where the window states bounds (scale error, heading drift per metre: its
    source's, ``window``) and the owner's map was built under stated bounds too
    (`owner_bounds`), the relative bend of the two maps is bounded by their sum (``how =
    "sum"``), or in quadrature when the two drifts are taken as independent (``"rss"``);
    ``"own"`` states the window's alone. Either unknown: none stated, the relative bend is
    fitted from the inliers (as for a window of unknown odometry). The residual tilt allowed
    (``max_tilt_deg``, each map levelled by its own rover's IMU) is combined by the same rule.

    `owner_sigma` (m, deg): how well the pose is known without this fix. Position: the larger
    of the owner's uncertainty over the registration's inliers and the rover's own; a shared
    fix enters the pose graph with the owner's uncertainty added to the registration's and is
    used only when that is well below the rover's own (:meth:`_Rover.try_shared`), so the
    registration need not be more precise than either. Rotation: the larger of the owner's and
    the pose graph's own yaw prediction (its gate model); the fix is a pose fix whose yaw
    enters with the registration's predicted rotation error added, so a rotation known less
    well than the rover's heading still fixes the position (the predicted position error at
    the rover already holds the rotation's lever). The limits on the predicted position and
    rotation error (``max_predicted_error_m``, ``max_predicted_rotation_deg``) are raised to
    these where they are larger; two rovers good to centimetres keep the reference attempt's.

    Both maps hold landmarks from stereo detections, each as noisy as the one map of a
    reference attempt: the residual RMSE floor (``max_rmse_m``) is combined in quadrature."""
    window = replace(window, max_rmse_m=math.hypot(window.max_rmse_m, window.max_rmse_m))
    if owner_sigma is not None:
        window = replace(
            window,
            max_predicted_error_m=max(window.max_predicted_error_m, owner_sigma[0]),
            max_predicted_rotation_deg=max(window.max_predicted_rotation_deg, owner_sigma[1]),
        )
    own = stated_window_bounds(window)
    if own is None:
        return window
    if owner_bounds is None:
        return replace(window, odometry_scale_error=None, odometry_heading_drift_deg_per_m=None)
    if how == "own":
        return window
    comb = (lambda a, b: a + b) if how == "sum" else math.hypot
    # each map is levelled by its own rover's IMU, to within max_tilt_deg: the same rule
    return replace(
        window,
        odometry_scale_error=comb(own[0], owner_bounds[0]),
        odometry_heading_drift_deg_per_m=comb(own[1], owner_bounds[1]),
        max_tilt_deg=min(comb(window.max_tilt_deg, window.max_tilt_deg), 44.0),
    )


@dataclass(frozen=True)
class MultiRoverConfig:
    """Settings of a multi-rover playback (metres, seconds, degrees as named)."""

    run: RunConfig = field(
        default_factory=RunConfig
    )  # each rover's run (as `lunarloc run`: loop, localization, ...)
    share_maps: bool = False  # localize against the other rovers' live maps too
    share_refresh_s: float = (
        5.0  # a rover's live map is rebuilt at most this often (mission time) ...
    )
    max_shared_sigma_ratio: float = (
        0.75  # a shared fix is used only if its sigma < this x the rover's own prediction
    )
    # the odometry bounds a shared attempt states (:func:`shared_localization`): both maps are
    # bent by their rovers' odometry; "sum" adds the two rovers' bounds (worst case), "rss" adds
    # them in quadrature (independent drifts), "own" states the local window's alone
    shared_bounds: str = "sum"
    # the uncertainty of each rover's estimate (its live map's owner sigma, its own prediction in
    # the informativeness test, the crop): "source", its odometry's stated bounds over the distance
    # since its last fix (at most the gate's model); "windows", the same per loop window, windows
    # independent (sqrt growth); "gate", the pose graph's gate drift model
    sigma_model: str = "windows"
    site_tolerance_m: float = 0.5  # the archives' landers must agree this well in the map frame
    site_tolerance_deg: float = 5.0  # ... and in heading
    clock_tolerance: float = 0.01  # relative difference of the archives' tick periods allowed

    def __post_init__(self) -> None:
        bad = [
            f"{n}={getattr(self, n)}"
            for n in (
                "share_refresh_s",
                "max_shared_sigma_ratio",
                "site_tolerance_m",
                "site_tolerance_deg",
                "clock_tolerance",
            )
            if not getattr(self, n) > 0
        ]
        if bad:
            raise ConfigError(f"{', '.join(bad)}: must be > 0")
        if self.sigma_model not in ("windows", "source", "gate"):
            raise ConfigError(f"sigma_model={self.sigma_model!r}: use windows, source or gate")
        if self.shared_bounds not in SHARED_BOUNDS:
            raise ConfigError(
                f"shared_bounds={self.shared_bounds!r}: use one of {', '.join(SHARED_BOUNDS)}"
            )

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data) -> MultiRoverConfig:
        """From :meth:`to_dict`'s output (ConfigError naming a bad key)."""
        return config_from_dict(cls, data)


@dataclass
class SharedAttempt:
    """One localization of a rover's local map in another rover's live map."""

    rover: str
    owner: str  # whose live map
    time_s: float
    frame: int
    landmarks: int  # local-map landmarks
    owner_landmarks: int  # live-map landmarks near the predicted position
    success: bool  # localize() trusted its answer
    accepted: bool  # ... and the fix was informative and passed the gate
    inliers: int = 0
    reason: str = ""
    predicted_error_m: float = float("nan")  # the registration's own
    owner_sigma_m: float = float("nan")  # largest owner sigma among the inliers
    owner_sigma_yaw_deg: float = float("nan")
    fix_sigma_m: float = float("nan")  # what the fix entered the pose graph with
    fix_sigma_yaw_deg: float = float("nan")
    own_sigma_m: float = float("nan")  # the rover's own predicted sigma at the keyframe
    correction_m: float = float("nan")
    gate_d2: float = float("nan")
    fix_error_m: float = float(
        "nan"
    )  # |fix - ground truth| (evaluation only; for a refused registration, what it would have been)


@dataclass
class RoverRun:
    """One rover's outcome: its run (the layout of ``lunarloc run``) and its shared attempts."""

    name: str
    archive: Path
    result: LoopResult
    shared: list[SharedAttempt]


@dataclass
class MultiRoverResult:
    rovers: list[RoverRun]
    config: dict

    def summary(self) -> dict:
        out = {"rovers": []}
        for r in self.rovers:
            s = r.result.summary()
            row = {
                "name": r.name,
                "archive": str(r.archive),
                "path_length_m": s["path_length_m"],
                "fixes": s["fixes"],
                "shared_fixes": sum(a.accepted for a in r.shared),
                "shared_attempts": len(r.shared),
            }
            acc = [a.fix_error_m for a in r.shared if a.accepted and math.isfinite(a.fix_error_m)]
            row["max_shared_fix_error_m"] = round(max(acc), 4) if acc else None
            # the worst accepted shared fix in units of the sigma it entered the pose graph with
            rel = [
                a.fix_error_m / a.fix_sigma_m
                for a in r.shared
                if a.accepted and math.isfinite(a.fix_error_m) and a.fix_sigma_m > 0
            ]
            row["max_shared_fix_error_sigmas"] = round(max(rel), 2) if rel else None
            for k in ("ate_odometry", "ate_corrected", "ate_online"):
                if k in s:
                    row[k] = s[k]
            out["rovers"].append(row)
        return out


# --------------------------------------------------------------------------- input checks


def _site_id(description: str) -> str | None:
    """The site a lunarloc-simulated archive names in its description (``site seed N``)."""
    m = re.search(r"site seed (\d+)", description or "")
    return m.group(1) if m else None


def check_archives(
    paths: Sequence[str | os.PathLike], config: MultiRoverConfig | None = None
) -> list[Path]:
    """Check that `paths` are distinct readable archives of one site on one clock; returns them
    as Paths. Raises InputError (one line, naming the files) otherwise."""
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.io.inputs import check_input_file

    cfg = config or MultiRoverConfig()
    if len(paths) < 2:
        raise InputError(f"several rovers need at least two archives, got {len(paths)}")
    out = [check_input_file(p, None, ".lac archive") for p in paths]
    for i, a in enumerate(out):
        for b in out[:i]:
            if os.path.samefile(a, b):
                raise InputError(f"{a}: the same archive is given twice (also as {b})")
    facts = []
    for p in out:
        with LacArchive(p) as ar:
            t = np.asarray(ar.frames["mission_time"], float)
            poses = np.asarray(ar.poses(), float)
            facts.append(
                {
                    "dt": float(np.median(np.diff(t))) if len(t) > 1 else float("nan"),
                    "lander": np.asarray(ar.lander_pose_map(), float),
                    "site": _site_id(ar.metadata.get("description", "")),
                    "poses": poses,
                }
            )
    a0, f0 = out[0], facts[0]
    for p, f in zip(out[1:], facts[1:]):
        if f0["poses"].shape == f["poses"].shape and np.array_equal(f0["poses"], f["poses"]):
            raise InputError(
                f"{p}: the same traverse as {a0} (identical poses): one archive given twice"
            )
        if f0["site"] is not None and f["site"] is not None and f0["site"] != f["site"]:
            raise InputError(
                f"{p}: site seed {f['site']}, but {a0} is of site seed {f0['site']}: "
                "rovers on one clock must share one site"
            )
        d = float(np.linalg.norm(f["lander"][:2] - f0["lander"][:2]))
        dyaw = abs(math.degrees(math.remainder(f["lander"][5] - f0["lander"][5], 2 * math.pi)))
        if d > cfg.site_tolerance_m or dyaw > cfg.site_tolerance_deg:
            raise InputError(
                f"{p}: its lander is {d:.2f} m / {dyaw:.1f} deg from {a0}'s in the map frame: "
                "archives of different sites (or map frames) cannot share one clock"
            )
        if not (math.isfinite(f["dt"]) and math.isfinite(f0["dt"])):
            raise InputError(
                f"{p if not math.isfinite(f['dt']) else a0}: fewer than two frames; nothing to play"
            )
        if abs(f["dt"] - f0["dt"]) > cfg.clock_tolerance * f0["dt"]:
            raise InputError(
                f"{p}: ticks every {f['dt']:.4f} s but {a0} every {f0['dt']:.4f} s: "
                "archives of different clocks"
            )
    return out


def rover_names(paths: Sequence[Path]) -> list[str]:
    """Folder-safe names, the archives' stems made unique."""
    names: list[str] = []
    for p in paths:
        base = re.sub(r"[^A-Za-z0-9_.-]+", "_", p.stem) or "rover"
        name, n = base, 2
        while name in names:
            name, n = f"{base}_{n}", n + 1
        names.append(name)
    return names


# --------------------------------------------------------------------------- one rover


@dataclass
class _LiveMap:
    """A rover's landmarks in its current ``map`` estimate, with the owner's sigma per landmark."""

    landmarks: LandmarkMap
    owner_sigma_m: np.ndarray
    owner_sigma_yaw_rad: np.ndarray
    key: tuple
    built_t: float


class _Rover:
    def __init__(self, name: str, path: Path, reference: LandmarkMap | None, cfg: MultiRoverConfig):
        from lunarloc.io.lac.archive import LacArchive
        from lunarloc.io.lac.playback import PlaybackAgent
        from lunarloc.odometry.source import archive_odometry, default_odometry_source
        from lunarloc.online.component import CameraRig, OnlineConfig, OnlineLocalizer

        self.name, self.path = name, path
        self.archive = LacArchive(path)
        self.agent = PlaybackAgent(self.archive)
        ar, agent = self.archive, self.agent
        self.timings = {"odometry": 0.0, "update": 0.0, "sharing": 0.0, "io": 0.0}
        t0 = time.perf_counter()
        o = cfg.run.odometry
        od = archive_odometry(
            ar, o.source or default_odometry_source(ar), imu_config=o.imu, visual_config=o.visual
        )
        T0 = agent.get_initial_position().matrix()
        # odometry starts at the initial pose (as the component anchors it), so the odometry
        # written to the run folder is the one the rover's corrections apply to
        A = T0 @ invert_transform(od.T_map_rover[0]) if len(od.frames) else np.eye(4)
        self.odometry = {int(f): A @ T for f, T in zip(od.frames, od.T_map_rover)}
        self.odometry_label = od.label
        self.timings["odometry"] = time.perf_counter() - t0
        rig = CameraRig.from_sensors(
            agent.sensors(), {c: agent.get_camera_position(c) for c in ar.cameras}
        )
        # the run folder holds the whole history, so the pose graph is never re-anchored
        online = OnlineConfig(
            loop=cfg.run.loop, localization=cfg.run.localization, max_keyframes=10**9
        )
        self.has_reference = reference is not None
        detector_config = cfg.run.detector_for(rig.camera.width)
        lander = ar.initial.get(
            "lander"
        )  # rover-relative at the start; detections on the lander are dropped
        # without a reference every attempt ends "no reference map" (recorded by the loop,
        # dropped from the outputs) and only shared fixes correct the rover
        self.loc = OnlineLocalizer(reference, T0, online, rig, detector_config, lander)
        # the odometry fed to it is the run's source: its windows state that source's bounds, as
        # `lunarloc run` does (not a caller's odometry of unknown accuracy, whose bend is fitted)
        self.loc.set_caller_odometry(od.label)
        # the bounds this rover's map is built under (its windows' before any calibration), for
        # the rovers localizing in it; None: not known (the bend is fitted)
        self.map_bounds = stated_window_bounds(self.loc.loop.localization)
        self.detector_config = self.loc.detector.config
        self.camera = rig.camera
        self.rocks = (
            ar.custom("rocks").to_array(("id", "x", "y", "z", "radius"))
            if "rocks" in ar.custom_records
            else None
        )
        self.ticks: list[tuple[int, float]] = []
        # per tick, 4x4: the component's estimate, ground truth, odometry
        self.T_map_rover_online: list[np.ndarray] = []
        self.T_map_rover_true: list[np.ndarray] = []
        self.T_odo_rover: list[np.ndarray] = []
        self.n_image = 0
        self.shared: list[SharedAttempt] = []
        self.shared_att: list[Attempt] = []
        self.anchor = (0.0, 0.0)  # (m, rad) sigma of the rover's last fix when it was a shared one
        self.sigma_model = cfg.sigma_model
        self.live: _LiveMap | None = None

    def close(self) -> None:
        self.agent.close()
        self.archive.close()

    @property
    def mission_time(self) -> float:
        return float(self.agent.get_mission_time())

    # ------------------------------------------------------------------ one tick
    def tick(self) -> object:
        t0 = time.perf_counter()
        a = self.agent
        f, t = a.frame, a.get_mission_time()
        if f not in self.odometry:
            raise InputError(f"{self.path}: no odometry pose at frame {f}")
        data = a.input_data()
        imu, v, w = a.get_imu_data(), a.get_linear_speed(), a.get_angular_speed()
        T_true = a.get_transform_matrix()
        t1 = time.perf_counter()
        est = self.loc.update(t, data, imu, v, w, odometry=self.odometry[f])
        t2 = time.perf_counter()
        self.timings["io"] += t1 - t0
        self.timings["update"] += t2 - t1
        self.ticks.append((int(f), float(t)))
        self.T_map_rover_online.append(est.T_map_rover)
        self.T_map_rover_true.append(T_true)
        self.T_odo_rover.append(self.odometry[f])
        self.n_image += int(
            any(img is not None for img in (data or {}).get("Grayscale", {}).values())
        )
        if est.attempt is not None and est.attempt.accepted:
            self.anchor = (
                0.0,
                0.0,
            )  # a reference fix: the rover's error no longer inherits another's
        return est

    # ------------------------------------------------------------------ live map
    def sigma(self, k: int) -> tuple[float, float]:
        """(position m, yaw rad) sigma of keyframe k's estimate in ``map``, without the inherited
        part: the odometry's stated bounds (scale error s, heading drift d per metre) over the
        distance D since the last fix, from the gate's base sigmas b, b_yaw: yaw = hypot(b_yaw,
        d D), position sqrt(b^2 + (s D)^2 + (yaw D / 2)^2) (``sigma_model = "source"``; the
        form :meth:`~lunarloc.online.loop.LoopState.crop_sigma_m` sizes a reference crop with;
        ``"windows"``: the bounds hold per loop window of L = ``window_m`` metres, the windows'
        errors independent, so beyond one window D in the scale and heading terms becomes
        sqrt(L D)),
        at most the gate's drift model; the gate's model itself where the bounds are not stated,
        stated 0, or ``sigma_model = "gate"``."""
        loop = self.loc.loop
        gate_m, gate_yaw = loop.graph.predicted_sigma(k)
        b = self.map_bounds
        if self.sigma_model == "gate" or b is None or b == (0.0, 0.0):
            return gate_m, gate_yaw
        g = loop.config.fusion.gate
        dd = loop.graph.distance_since_fix(k)
        # "windows": the bounds hold per window of window_m metres (what they were measured on),
        # the windows' errors independent: they grow with sqrt(window_m D) beyond one window
        L = loop.config.window_m
        de = math.sqrt(L * dd) if self.sigma_model == "windows" and dd > L else dd
        yaw = math.hypot(math.radians(g.base_sigma_yaw_deg), math.radians(b[1]) * de)
        pos = math.sqrt(g.base_sigma_m**2 + (b[0] * de) ** 2 + (0.5 * yaw * dd) ** 2)
        return min(pos, gate_m), min(yaw, gate_yaw)

    def owner_sigmas(self) -> tuple[np.ndarray, np.ndarray]:
        """(position m, yaw rad) sigma of every keyframe's estimate in ``map`` (:meth:`sigma`),
        with the inherited sigma of its last fix when that was a shared one."""
        n = len(self.loc.loop.keyframes)
        s = np.array([self.sigma(k) for k in range(n)], float).reshape(-1, 2)
        return np.hypot(s[:, 0], self.anchor[0]), np.hypot(s[:, 1], self.anchor[1])

    def live_map(self, t: float, refresh_s: float) -> _LiveMap | None:
        """This rover's landmarks so far, placed with its current estimates (cached)."""
        from scipy.spatial import cKDTree

        loop = self.loc.loop
        n = len(loop.keyframes)
        key = (n, len(loop.graph.fixes), self.anchor)
        if self.live is not None and (self.live.key == key or t - self.live.built_t < refresh_s):
            return self.live
        if n == 0:
            return None
        P, F = loop.window_points(np.arange(n), loop.graph.poses())
        if len(P) == 0:
            return None
        agg = loop.config.aggregation
        lm = aggregate_detections(P, F, agg, frame="map")
        s_m, s_y = self.owner_sigmas()
        om, oy = np.zeros(len(lm)), np.zeros(len(lm))
        if len(lm):
            groups = cKDTree(P).query_ball_point(lm.positions_xyz, r=agg.radius_m)
            for i, idx in enumerate(groups):
                kf = (
                    F[np.asarray(idx, int)]
                    if len(idx)
                    else F[[int(np.argmin(np.linalg.norm(P - lm.positions_xyz[i], axis=1)))]]
                )
                om[i], oy[i] = float(np.median(s_m[kf])), float(np.median(s_y[kf]))
        self.live = _LiveMap(lm, om, oy, key, t)
        return self.live

    # ------------------------------------------------------------------ shared attempt
    def try_shared(
        self,
        others: Sequence[_Rover],
        refresh_s: float,
        max_ratio: float = 0.75,
        shared_bounds: str = "sum",
    ) -> SharedAttempt | None:
        """Localize the newest keyframe's local map in the other rovers' live maps; the first
        accepted fix enters the pose graph. Returns the last attempt made (None: no local map)."""
        from lunarloc.localization.localize import localize

        t_start = time.perf_counter()
        loop = self.loc.loop
        cfg = loop.config
        k = len(loop.keyframes) - 1
        f, t = self.ticks[-1]
        poses = loop.graph.poses()
        # the local map of the reference attempt: its (adaptive) window, sighting arcs and all
        win, _, _, _, veh, _ = loop.local_map(k, poses)
        if len(veh) < cfg.min_window_landmarks:
            self.timings["sharing"] += time.perf_counter() - t_start
            return None
        own_m, own_yaw = self.sigma(k)
        own_m, own_yaw = math.hypot(own_m, self.anchor[0]), math.hypot(own_yaw, self.anchor[1])
        gate_yaw = math.hypot(
            loop.graph.predicted_sigma(k)[1], self.anchor[1]
        )  # the pose graph's own yaw prediction
        c = veh.positions_xyz[:, :2].mean(axis=0)
        radius = float(np.max(np.linalg.norm(veh.positions_xyz[:, :2] - c, axis=1)))
        att = None
        for other in sorted(others, key=lambda o: o.name):
            live = other.live_map(t, refresh_s)
            if live is None or len(live.landmarks) < 3:
                continue
            # the crop allows for both rovers' uncertainty, per owner landmark
            d = np.linalg.norm(live.landmarks.positions_xyz[:, :2] - c, axis=1)
            near = np.flatnonzero(
                d
                <= radius
                + cfg.crop_sigmas * np.hypot(own_m, live.owner_sigma_m)
                + cfg.crop_margin_m
            )
            att = SharedAttempt(
                self.name, other.name, t, f, len(veh), len(near), False, False, own_sigma_m=own_m
            )
            self.shared.append(att)
            if len(near) < 3:
                att.reason = (
                    f"{other.name}'s live map has {len(near)} landmarks near the predicted position"
                )
                continue
            ref = live.landmarks.subset(near)
            try:
                # as the reference attempt: the pose judged at the rover now, along the window's path
                window_cfg = loop.window_localization()
                lcfg = shared_localization(window_cfg, other.map_bounds, shared_bounds)
                res = localize(
                    ref, veh, lcfg, query_xyz=poses[k : k + 1, :3], path_xyz=poses[win, :3]
                )
                # refused for precision alone where the owner's map is less precise than the limits:
                # judged again with the limits at the owner's sigma over these inliers (the search is
                # deterministic, so the same registration; every other check as before)
                if not res.success and len(res.inliers):
                    owner = (
                        max(float(np.max(live.owner_sigma_m[res.inliers[:, 1]])), own_m),
                        math.degrees(
                            max(
                                float(np.max(live.owner_sigma_yaw_rad[res.inliers[:, 1]])), gate_yaw
                            )
                        ),
                    )
                    imprecise = not (
                        res.predicted_error_m <= lcfg.max_predicted_error_m
                        and res.predicted_rotation_deg <= lcfg.max_predicted_rotation_deg
                    )
                    if imprecise and (
                        owner[0] > lcfg.max_predicted_error_m
                        or owner[1] > lcfg.max_predicted_rotation_deg
                    ):
                        lcfg = shared_localization(
                            window_cfg, other.map_bounds, shared_bounds, owner
                        )
                        res = localize(
                            ref, veh, lcfg, query_xyz=poses[k : k + 1, :3], path_xyz=poses[win, :3]
                        )
            except LunarLocError as exc:
                att.reason = f"{type(exc).__name__}: {exc}"
                continue
            att.inliers, att.success, att.reason = res.num_inliers, bool(res.success), res.reason
            att.predicted_error_m = float(res.predicted_error_m)
            x, y, z, yaw = poses[k]
            roll, pitch = loop.keyframes[k].roll_pitch_rad
            if np.all(
                np.isfinite(res.T_ref_veh)
            ):  # what the fix would be (evaluation, refused ones too)
                T_fix = res.T_ref_veh @ pose_to_matrix(x, y, z, roll, pitch, yaw)
                att.fix_error_m = float(
                    np.linalg.norm(T_fix[:3, 3] - self.T_map_rover_true[-1][:3, 3])
                )
            if not res.success:
                continue
            fix4 = np.array([T_fix[0, 3], T_fix[1, 3], T_fix[2, 3], yaw_of(T_fix[:3, :3])])
            inl = res.inliers
            Vp = veh.positions_xyz[inl[:, 0]]
            extent = max(
                float(np.max(np.linalg.norm(Vp[:, :2] - Vp[:, :2].mean(axis=0), axis=1))), 1.0
            )
            pred = (
                float(res.predicted_error_m)
                if math.isfinite(res.predicted_error_m)
                else cfg.fix_sigma_fallback_m
            )
            om = float(np.max(live.owner_sigma_m[near[inl[:, 1]]]))
            oy = float(np.max(live.owner_sigma_yaw_rad[near[inl[:, 1]]]))
            # the registration's rotation error (its predicted one, else position over extent) and the owner's
            rot = (
                math.radians(res.predicted_rotation_deg)
                if math.isfinite(res.predicted_rotation_deg)
                else pred / extent
            )
            sig_m, sig_yaw = math.hypot(pred, om), math.hypot(rot, oy)
            att.owner_sigma_m, att.owner_sigma_yaw_deg = om, math.degrees(oy)
            att.fix_sigma_m, att.fix_sigma_yaw_deg = sig_m, math.degrees(sig_yaw)
            if sig_m >= max_ratio * own_m:
                att.reason = (
                    f"not informative: the fix ({sig_m * 100:.0f} cm, {other.name}'s estimate "
                    f"{om * 100:.0f} cm) is not below {max_ratio:g} x the rover's own prediction ({own_m * 100:.0f} cm)"
                )
                continue
            g = loop.graph.gate(k, fix4, sig_m, sig_yaw)
            att.gate_d2, att.correction_m = g.d2, float(np.linalg.norm(g.innovation[:3]))
            if not g.accepted:
                att.reason = f"fix rejected by the gate (d2 {g.d2:.1f} > {g.threshold:.1f}; correction {att.correction_m:.2f} m)"
                continue
            loop.graph.add_fix(k, fix4, sig_m, sig_yaw)
            loop.graph.solve(cfg.active_window_m)
            att.accepted = True
            self.anchor = (sig_m, sig_yaw)
            break
        if att is not None:
            self.shared_att.append(self._as_attempt(att, k, fix4 if att.accepted else None))
        self.timings["sharing"] += time.perf_counter() - t_start
        return att

    @staticmethod
    def _as_attempt(s: SharedAttempt, k: int, fix4) -> Attempt:
        """A shared attempt as a row of the run's attempts (``reason`` names the owner; with
        several owners, the accepted or last one; rovers.json has them all)."""
        a = Attempt(
            s.frame,
            s.time_s,
            k,
            s.landmarks,
            s.owner_landmarks,
            s.success,
            s.accepted,
            s.inliers,
            f"map of {s.owner}: {s.reason}" if s.reason else f"map of {s.owner}",
            s.correction_m,
            float("nan"),
            s.gate_d2,
            s.predicted_error_m,
            s.fix_error_m if s.success else float("nan"),
        )
        if fix4 is not None:
            a.fix_xyz = [float(v) for v in fix4[:3]]
        return a

    # ------------------------------------------------------------------ end
    def finish(self, reference: LandmarkMap | None, config: MultiRoverConfig) -> RoverRun:
        loop = self.loc.loop
        attempts = list(loop.attempts) if self.has_reference else []
        attempts = sorted(
            attempts + self.shared_att, key=lambda a: (a.time_s, a.reason.startswith("map of"))
        )
        kf = loop.finish(self.n_image)  # final solve; keyframe-rate trajectories
        T_kf = loop.graph.correction_transforms()
        frames = np.array([f for f, _ in self.ticks], int)
        times = np.array([t for _, t in self.ticks], float)
        T_odo = np.asarray(self.T_odo_rover).reshape(-1, 4, 4)
        corrected = interpolate_corrections(T_kf, np.asarray(loop.times), times, T_odo)
        # the run's configuration as a single run writes it (read back by `lunarloc run --config`)
        info = {
            "archive": str(self.path),
            "odometry_source": self.odometry_label,
            "camera": asdict(self.camera),
            "detector_scaled": self.detector_config.to_dict(),
            "multirover": {k: v for k, v in config.to_dict().items() if k != "run"},
        }
        ref = reference if reference is not None else LandmarkMap(np.zeros((0, 3)), frame="map")
        res = LoopResult(
            frames,
            times,
            T_odo,
            np.asarray(self.T_map_rover_online).reshape(-1, 4, 4),
            corrected,
            np.asarray(self.T_map_rover_true).reshape(-1, 4, 4),
            attempts,
            kf.vehicle_map,
            kf.vehicle_map_odometry,
            ref,
            dict(self.timings),
            self.n_image,
            {**config.run.to_dict(), "info": info},
            kf.scale,
            self.rocks,
            None,
            str(self.path),
        )
        return RoverRun(self.name, self.path, res, self.shared)


# --------------------------------------------------------------------------- the driver


def run_rovers(
    archives: Sequence[str | os.PathLike],
    reference: LandmarkMap | Sequence[LandmarkMap | None] | None = None,
    config: MultiRoverConfig | None = None,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> MultiRoverResult:
    """Play `archives` on one mission clock (see the module docstring).

    reference : map in the ``map`` frame for every rover, or None (then ``share_maps`` must
        be on: the rovers can only align to each other), or one map or None per archive.
    config.run : each rover's :class:`~lunarloc.config.run.RunConfig` (the detector is scaled to
        each archive's image width; odometry source default per archive: ``visual`` when it
        has front stereo pairs, else ``imu``).
    progress(done, total) : ticks played over all rovers.
    """
    cfg = config or MultiRoverConfig()
    refs = list(reference) if isinstance(reference, (list, tuple)) else [reference] * len(archives)
    if len(refs) != len(archives):
        raise ConfigError(
            f"{len(refs)} reference maps for {len(archives)} archives: give one, or one per archive"
        )
    if any(r is None for r in refs) and not cfg.share_maps:
        raise ConfigError(
            "a rover without a reference map needs share_maps (--share-maps): "
            "there is nothing else to localize against"
        )
    paths = check_archives(archives, cfg)
    names = rover_names(paths)
    rovers: list[_Rover] = []
    try:
        for name, p, ref in zip(names, paths, refs):
            rovers.append(_Rover(name, p, ref, cfg))
        total = sum(len(r.archive.frame_numbers) for r in rovers)
        heap = [(r.mission_time, i) for i, r in enumerate(rovers)]
        heapq.heapify(heap)
        done = 0
        while heap:
            _, i = heapq.heappop(heap)
            r = rovers[i]
            est = r.tick()
            if cfg.share_maps and est.attempt is not None and not est.attempt.accepted:
                r.try_shared(
                    [o for o in rovers if o is not r],
                    cfg.share_refresh_s,
                    cfg.max_shared_sigma_ratio,
                    cfg.shared_bounds,
                )
            done += 1
            if progress:
                progress(done, total)
            if not r.agent.at_end():
                r.agent.step_frame()
                heapq.heappush(heap, (r.mission_time, i))
        for r in rovers:
            if r.n_image == 0:
                raise InputError(f"{r.path}: no image frames were played; nothing to localize")
        runs = [r.finish(ref, cfg) for r, ref in zip(rovers, refs)]
    finally:
        for r in rovers:
            r.close()
    return MultiRoverResult(
        runs, {"archives": [str(p) for p in paths], "names": names, **cfg.to_dict()}
    )


def write_rover_outputs(
    result: MultiRoverResult, outdir: str | os.PathLike, plot: bool = True
) -> list[Path]:
    """One run folder per rover (``OUT/<name>/``, the layout of ``lunarloc run``), ``rovers.json``
    (per-rover summary, every shared attempt, the config) and, with `plot`, ``map_all.png``
    (every rover: ground truth, odometry, corrected, landmarks) plus each run's figures.
    Returns the files written at the top level."""
    import json

    from lunarloc.io.outputs import make_dir, write_text
    from lunarloc.io.runs import to_json_ready, write_run

    out = make_dir(outdir)
    if plot:
        from lunarloc.viz import plot_run
    for (
        r
    ) in result.rovers:  # each rover's figures before its summary.json (a complete folder's mark)
        write_run(
            r.result,
            out / r.name,
            before_summary=(lambda s, d=out / r.name: plot_run(d, summary=s)) if plot else None,
        )
    doc = {
        **result.summary(),
        "shared_attempts": {r.name: [asdict(a) for a in r.shared] for r in result.rovers},
        "config": result.config,
    }
    written = []
    if plot:
        from lunarloc.viz import plot_rovers

        written.append(
            plot_rovers(
                [out / r.name for r in result.rovers],
                out / "map_all.png",
                [r.name for r in result.rovers],
            )
        )
    write_text(out / "rovers.json", json.dumps(to_json_ready(doc), indent=1, default=str))
    written.insert(0, out / "rovers.json")
    return written
