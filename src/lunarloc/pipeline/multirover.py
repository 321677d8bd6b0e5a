"""Several rovers on one clock: archives played in mission-time order, each rover localizing
against a reference map and/or the other rovers' live maps (LunarLoc's multi-agent playback).

``run_rovers([a.lac, b.lac], reference=None, config=MultiRoverConfig(share_maps=True))``
(every rover runs with ``config.run``, the :class:`~lunarloc.config.run.RunConfig` of ``lunarloc
run``):

1. **one clock**: every archive is a :class:`~lunarloc.io.lac.playback.PlaybackAgent`; at each
   step the rover whose next tick is earliest in mission time is played (ties: argument order);
2. **per rover**: one :class:`~lunarloc.online.component.OnlineLocalizer` per rover, fed tick by
tick
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
when it was itself a shared fix (a rover aligned to another inherits that rover's error).

Two rovers fuse (``shared_fusion="split"``): an accepted registration measures the difference
of the two rovers' errors at that place, so each moves by its share of the innovation
(:func:`split_shared_fix`), the owner at its keyframe that saw most of the inliers; a later
registration between the same two rovers over the same keyframes, either way round, is refused
(:func:`repeated_exchange`), so one tie is not counted twice. ``"one-way"``: the rover takes
the registration as a fix, only when it is clearly more certain than its own prediction.
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
from lunarloc.online.loop import (
    Attempt,
    LoopResult,
    gate_fix,
    interpolate_corrections,
    stated_window_bounds,
)
from lunarloc.io.maps import LandmarkMap, aggregate_detections

if TYPE_CHECKING:
    from lunarloc.localization.config import LocalizationConfig

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "MultiRoverConfig",
    "SharedAttempt",
    "SharedSplit",
    "split_shared_fix",
    "Exchange",
    "repeated_exchange",
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
    window = replace(
        window, max_rmse_m=math.hypot(window.acceptance.max_rmse_m, window.acceptance.max_rmse_m)
    )
    if owner_sigma is not None:
        window = replace(
            window,
            max_predicted_error_m=max(window.acceptance.max_predicted_error_m, owner_sigma[0]),
            max_predicted_rotation_deg=max(
                window.acceptance.max_predicted_rotation_deg, owner_sigma[1]
            ),
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
        max_tilt_deg=min(comb(window.search.max_tilt_deg, window.search.max_tilt_deg), 44.0),
    )


@dataclass(frozen=True)
class SharedSplit:
    """How one registration between two rovers moves each of them (:func:`split_shared_fix`).

    weights: the share of the innovation (the registration's fix minus the rover's estimate)
    each moves by, position and yaw; the rover towards the fix, the owner the other way.
    sigmas: each one's sigma after the move (m, rad)."""

    rover_weight_m: float
    rover_weight_yaw: float
    owner_weight_m: float
    owner_weight_yaw: float
    rover_sigma_m: float
    rover_sigma_yaw_rad: float
    owner_sigma_m: float
    owner_sigma_yaw_rad: float


def split_shared_fix(
    rover_sigma: tuple[float, float],
    owner_sigma: tuple[float, float],
    registration_sigma: tuple[float, float],
) -> SharedSplit:
    """Fuse two rovers' estimates of one place through a registration of one's local map in
    the other's live map: a relative constraint between the two, not one taken as truth.

    Each sigma is (position m, yaw rad): the rover's own estimate at the keyframe, the owner's
    over the registration's inliers, the registration's own predicted error. The registration
    measures the difference of the two rovers' errors there (plus its own); with variances
    ``V_r``, ``V_o``, ``V_reg`` and ``S`` their sum, the least-squares estimate moves the rover
    by ``V_r / S`` of the innovation towards the fix and the owner by ``V_o / S`` the other
    way, and leaves them with sigmas ``sqrt(V_r (V_o + V_reg) / S)`` and ``sqrt(V_o (V_r +
    V_reg) / S)``. Equal sigmas: both move halfway (less the registration's share). A rover
    far more certain than the other hardly moves; the other then takes nearly the whole fix,
    as a fix from a reference."""
    vals = [float(v) for v in (*rover_sigma, *owner_sigma, *registration_sigma)]
    if not all(math.isfinite(v) and v >= 0 for v in vals):
        raise ConfigError(f"sigmas {vals}: must be finite and >= 0")
    out = []
    for vr, vo, vg in ((vals[0], vals[2], vals[4]), (vals[1], vals[3], vals[5])):
        vr, vo, vg = vr * vr, vo * vo, vg * vg
        S = vr + vo + vg
        if S <= 0:
            out.append((0.0, 0.0, 0.0, 0.0))
            continue
        out.append((vr / S, vo / S, math.sqrt(vr * (vo + vg) / S), math.sqrt(vo * (vr + vg) / S)))
    (wr, wo, sr, so), (wry, woy, sry, soy) = out
    return SharedSplit(wr, wry, wo, woy, sr, sry, so, soy)


@dataclass(frozen=True)
class Exchange:
    """One accepted shared registration: which keyframes of each rover it used (first, last).
    ``moved``: the rovers it moved."""

    id: int
    time_s: float
    keyframes: dict  # rover name -> (first, last) keyframe index
    moved: tuple


def _overlap(cur: tuple[int, int], prev: tuple[int, int]) -> float:
    """The common part of two keyframe ranges (inclusive) as a share of the shorter: 1 when one
    holds the other (an owner's inliers seen over a long stretch still overlap a window)."""
    lo, hi = max(cur[0], prev[0]), min(cur[1], prev[1])
    n = min(cur[1] - cur[0] + 1, prev[1] - prev[0] + 1)
    return max(hi - lo + 1, 0) / max(n, 1)


def repeated_exchange(
    ledger: Sequence[Exchange],
    rover: str,
    rover_keyframes: tuple[int, int],
    owner: str,
    owner_keyframes: tuple[int, int],
    max_overlap: float,
) -> Exchange | None:
    """The earlier exchange between `rover` and `owner` (either way round: the same
    registration, or its mirror) whose keyframes overlap this one's by more than `max_overlap`
    on *both* sides, or None. Such a registration would count the same information twice: the
    two places were already tied together, and the first tie moved both estimates."""
    for e in ledger:
        if rover not in e.keyframes or owner not in e.keyframes:
            continue
        if (
            _overlap(rover_keyframes, e.keyframes[rover]) > max_overlap
            and _overlap(owner_keyframes, e.keyframes[owner]) > max_overlap
        ):
            return e
    return None


SHARED_FUSION = ("split", "one-way")


@dataclass(frozen=True)
class MultiRoverConfig:
    """Settings of a multi-rover playback (metres, seconds, degrees as named)."""

    # each rover's run (as `lunarloc run`: loop, localization, ...)
    run: RunConfig = field(default_factory=RunConfig)
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
    # how an accepted shared registration is used: "split", a relative constraint between the two
    # rovers (each moves by its share of the innovation, :func:`split_shared_fix`; the owner gets a
    # fix at the keyframes that saw the inliers); "one-way", the rover takes the registration as a
    # fix with the owner's sigma added, only when that is below max_shared_sigma_ratio x its own
    shared_fusion: str = "split"
    # "split": a rover (either side) is moved only when its weight is at least this much
    min_shared_weight: float = 0.2
    # "split": a registration whose keyframes overlap an earlier exchange's between the same two
    # rovers (either way round) by more than this on both sides is refused
    # (:func:`repeated_exchange`)
    max_exchange_overlap: float = 0.5
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
        if self.shared_fusion not in SHARED_FUSION:
            raise ConfigError(
                f"shared_fusion={self.shared_fusion!r}: use one of {', '.join(SHARED_FUSION)}"
            )
        for n in ("min_shared_weight", "max_exchange_overlap"):
            if not 0 <= getattr(self, n) <= 1:
                raise ConfigError(f"{n}={getattr(self, n)}: must be in [0, 1]")
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
    # |fix - ground truth| (evaluation only; for a refused registration, what it would have been)
    fix_error_m: float = float("nan")
    # shared_fusion "split": the share of the innovation this rover moved by, the owner's, the sigma
    # the rover's move entered its pose graph with and that position's |error| (evaluation only)
    weight: float = float("nan")
    owner_weight: float = float("nan")
    applied_sigma_m: float = float("nan")
    applied_error_m: float = float("nan")
    # this row is the owner's side of another rover's registration (`owner` made it in this
    # rover's live map); its fix is this rover's position moved the other way
    mirror: bool = False
    exchange: int = -1  # the exchange id (both sides' rows share it); -1: none


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
            for k in (
                "ate_odometry",
                "ate_corrected",
                "ate_online",
                "final_error_odometry_m",
                "final_error_corrected_m",
            ):
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
    # per landmark: the first and last of the owner's keyframes that saw it (the exchange guard)
    keyframes: np.ndarray | None = None
    # per landmark: the owner's sigma without the inherited part of its last (shared) fix
    drift_sigma_m: np.ndarray | None = None
    drift_sigma_yaw_rad: np.ndarray | None = None


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
        # rover-relative at the start; detections on the lander are dropped
        lander = ar.initial.get("lander")
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
        self.last_exchange: int | None = None  # the exchange that gave that fix ("split")
        self._applied = None  # the pose this rover was last moved to by an exchange
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
            # a reference fix: the rover's error no longer inherits another's
            self.anchor, self.last_exchange = (0.0, 0.0), None
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

    def owner_sigmas(self, inherited: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(position m, yaw rad) sigma of every keyframe's estimate in ``map`` (:meth:`sigma`),
        with (`inherited`) the inherited sigma of its last fix when that was a shared one."""
        n = len(self.loc.loop.keyframes)
        s = np.array([self.sigma(k) for k in range(n)], float).reshape(-1, 2)
        a = self.anchor if inherited else (0.0, 0.0)
        return np.hypot(s[:, 0], a[0]), np.hypot(s[:, 1], a[1])

    def live_map(self, t: float, refresh_s: float) -> _LiveMap | None:
        """This rover's landmarks so far, placed with its current estimates (cached)."""
        from scipy.spatial import cKDTree

        loop = self.loc.loop
        n = len(loop.keyframes)
        key = (n, len(loop.graph.fixes), self.anchor)
        # new keyframes: rebuilt at most every refresh_s; a new fix (it moved the landmarks) at once
        if self.live is not None and (
            self.live.key == key
            or (self.live.key[1:] == key[1:] and t - self.live.built_t < refresh_s)
        ):
            return self.live
        if n == 0:
            return None
        P, F = loop.window_points(np.arange(n), loop.graph.poses())
        if len(P) == 0:
            return None
        agg = loop.config.aggregation
        lm = aggregate_detections(P, F, agg, frame="map")
        s_m, s_y = self.owner_sigmas()
        d_m, d_y = self.owner_sigmas(inherited=False)
        om, oy = np.zeros(len(lm)), np.zeros(len(lm))
        dm, dy = np.zeros(len(lm)), np.zeros(len(lm))
        kfr = np.zeros((len(lm), 2), int)
        if len(lm):
            groups = cKDTree(P).query_ball_point(lm.positions_xyz, r=agg.radius_m)
            for i, idx in enumerate(groups):
                kf = (
                    F[np.asarray(idx, int)]
                    if len(idx)
                    else F[[int(np.argmin(np.linalg.norm(P - lm.positions_xyz[i], axis=1)))]]
                )
                om[i], oy[i] = float(np.median(s_m[kf])), float(np.median(s_y[kf]))
                dm[i], dy[i] = float(np.median(d_m[kf])), float(np.median(d_y[kf]))
                kfr[i] = int(np.min(kf)), int(np.max(kf))
        self.live = _LiveMap(lm, om, oy, key, t, kfr, dm, dy)
        return self.live

    # ------------------------------------------------------------------ shared attempt
    def try_shared(
        self,
        others: Sequence[_Rover],
        refresh_s: float,
        max_ratio: float = 0.75,
        shared_bounds: str = "sum",
        config: MultiRoverConfig | None = None,
        ledger: list[Exchange] | None = None,
    ) -> SharedAttempt | None:
        """Localize the newest keyframe's local map in the other rovers' live maps; the first
        accepted registration enters the pose graphs (``config.shared_fusion``: "split", both
        rovers' by their shares, :meth:`_exchange`; "one-way", this rover's as a fix). `ledger`:
        the exchanges so far, shared by all rovers (appended to). Returns the last attempt made
        (None: no local map)."""
        from lunarloc.localization.localize import localize

        mr_cfg = config or replace(
            MultiRoverConfig(), max_shared_sigma_ratio=max_ratio, shared_bounds=shared_bounds
        )
        mode = mr_cfg.shared_fusion
        ledger = [] if ledger is None else ledger
        fix4 = None

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
        # the pose graph's own yaw prediction
        gate_yaw = math.hypot(loop.graph.predicted_sigma(k)[1], self.anchor[1])
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
                # as the reference attempt: the pose judged at the rover now, along the window's
                # path
                window_cfg = loop.window_localization()
                lcfg = shared_localization(window_cfg, other.map_bounds, shared_bounds)
                res = localize(
                    ref, veh, lcfg, query_xyz=poses[k : k + 1, :3], path_xyz=poses[win, :3]
                )
                # refused for precision alone where the owner's map is less precise than the limits:
                # judged again with the limits at the owner's sigma over these inliers (the search
                # is
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
                        res.predicted_error_m <= lcfg.acceptance.max_predicted_error_m
                        and res.predicted_rotation_deg <= lcfg.acceptance.max_predicted_rotation_deg
                    )
                    if imprecise and (
                        owner[0] > lcfg.acceptance.max_predicted_error_m
                        or owner[1] > lcfg.acceptance.max_predicted_rotation_deg
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
            # the registration's rotation error (its predicted one, else position over extent) and
            # the owner's
            rot = (
                math.radians(res.predicted_rotation_deg)
                if math.isfinite(res.predicted_rotation_deg)
                else pred / extent
            )
            sig_m, sig_yaw = math.hypot(pred, om), math.hypot(rot, oy)
            att.owner_sigma_m, att.owner_sigma_yaw_deg = om, math.degrees(oy)
            att.fix_sigma_m, att.fix_sigma_yaw_deg = sig_m, math.degrees(sig_yaw)
            if mode == "split":
                kf_rover = (int(win.min()), int(win.max()))
                kr = live.keyframes[near[inl[:, 1]]] if live.keyframes is not None else None
                kf_owner = (
                    (int(kr[:, 0].min()), int(kr[:, 1].max())) if kr is not None else (-1, -1)
                )
                prev = repeated_exchange(
                    ledger, self.name, kf_rover, other.name, kf_owner, mr_cfg.max_exchange_overlap
                )
                if prev is not None:
                    att.reason = (
                        f"already exchanged: {other.name}'s landmarks and this window were tied "
                        f"at {prev.time_s:.1f} s (exchange {prev.id})"
                    )
                    continue
                if not gate_fix(loop.graph, att, k, fix4, sig_m, sig_yaw).accepted:
                    continue
                if self._exchange(
                    att,
                    other,
                    k,
                    poses[k],
                    fix4,
                    res.T_ref_veh,
                    (pred, rot),
                    (own_m, own_yaw),
                    (om, oy),
                    live,
                    near[inl[:, 1]],
                    kf_rover,
                    kf_owner,
                    ledger,
                    mr_cfg,
                ):
                    break
                continue
            if sig_m >= max_ratio * own_m:
                att.reason = (
                    f"not informative: the fix ({sig_m * 100:.0f} cm, {other.name}'s estimate "
                    f"{om * 100:.0f} cm) is not below {max_ratio:g} x the rover's own prediction "
                    f"({own_m * 100:.0f} cm)"
                )
                continue
            if not gate_fix(loop.graph, att, k, fix4, sig_m, sig_yaw).accepted:
                continue
            loop.graph.add_fix(k, fix4, sig_m, sig_yaw)
            loop.graph.solve(cfg.active_window_m)
            att.accepted = True
            self.anchor = (sig_m, sig_yaw)
            self.last_exchange = None
            break
        if att is not None:
            applied = self._applied if att.accepted and mode == "split" else fix4
            self.shared_att.append(self._as_attempt(att, k, applied if att.accepted else None))
        self.timings["sharing"] += time.perf_counter() - t_start
        return att

    def _exchange(
        self,
        att: SharedAttempt,
        other: _Rover,
        k: int,
        pose_k: np.ndarray,
        fix4: np.ndarray,
        T_ref_veh: np.ndarray,
        reg_sigma: tuple[float, float],
        own: tuple[float, float],
        owner: tuple[float, float],
        live: _LiveMap,
        inliers: np.ndarray,
        kf_rover: tuple[int, int],
        kf_owner: tuple[int, int],
        ledger: list[Exchange],
        mr_cfg: MultiRoverConfig,
    ) -> bool:
        """Use a trusted registration of keyframe k's window in `other`'s live map as a relative
        constraint between the two rovers (:func:`split_shared_fix`): this rover moves its share
        of the innovation towards the fix, `other` its share the other way at the keyframe that
        saw most of the inliers. When both rovers' last fixes were one exchange between them,
        the error that exchange left is common to both and cancels in the registration: the
        split uses the sigmas since then, and each keeps that common part. A side whose weight
        is below ``min_shared_weight`` (or whose keyframe is outside its pose graph's active
        window, or whose gate refuses its move) is not moved. Returns whether any side moved."""
        loop, oloop = self.loc.loop, other.loc.loop
        common = (
            self.last_exchange is not None
            and self.last_exchange == other.last_exchange
            and live.drift_sigma_m is not None
        )
        own_c, own_common = own, (0.0, 0.0)
        owner_c = owner
        if common:
            own_c = self.sigma(k)
            owner_c = (
                float(np.max(live.drift_sigma_m[inliers])),
                float(np.max(live.drift_sigma_yaw_rad[inliers])),
            )
            own_common = self.anchor
        sp = split_shared_fix(own_c, owner_c, reg_sigma)
        att.weight, att.owner_weight = sp.rover_weight_m, sp.owner_weight_m
        innov = np.asarray(fix4, float) - np.asarray(pose_k, float)
        innov[3] = math.remainder(innov[3], 2 * math.pi)
        w_min = mr_cfg.min_shared_weight
        moved = []
        # this rover: towards the fix
        if sp.rover_weight_m >= w_min:
            tgt = np.asarray(pose_k, float) + innov * np.array(
                [sp.rover_weight_m] * 3 + [sp.rover_weight_yaw]
            )
            s_m = math.hypot(sp.rover_sigma_m, own_common[0])
            s_y = math.hypot(sp.rover_sigma_yaw_rad, own_common[1])
            loop.graph.add_fix(k, tgt, s_m, s_y)
            loop.graph.solve(loop.config.active_window_m)
            att.applied_sigma_m = s_m
            att.applied_error_m = float(np.linalg.norm(tgt[:3] - self.T_map_rover_true[-1][:3, 3]))
            self._applied = tgt
            moved.append(self.name)
        # the owner: the other way, at its keyframe that saw most of the inliers
        orow = None
        if sp.owner_weight_m >= w_min and live.keyframes is not None:
            kr = live.keyframes[inliers]
            kb = round(float(np.median(kr.mean(axis=1))))
            first = oloop.graph.first_active(oloop.config.active_window_m)
            orow = SharedAttempt(
                other.name,
                self.name,
                att.time_s,
                att.frame,
                att.owner_landmarks,
                att.landmarks,
                True,
                False,
                att.inliers,
                "",
                att.predicted_error_m,
                own[0],
                math.degrees(own[1]),
                math.hypot(reg_sigma[0], own[0]),
                math.degrees(math.hypot(reg_sigma[1], own[1])),
                owner[0],
                mirror=True,
                weight=sp.owner_weight_m,
                owner_weight=sp.rover_weight_m,
            )
            other.shared.append(orow)
            xb = oloop.graph.pose(kb)
            R, t = T_ref_veh[:3, :3], T_ref_veh[:3, 3]
            d_b = (R - np.eye(3)) @ xb[:3] + t  # the registration's move at the owner's keyframe
            full = np.concatenate([xb[:3] - d_b, [xb[3] - innov[3]]])
            tgt = xb + np.concatenate([-d_b * sp.owner_weight_m, [-innov[3] * sp.owner_weight_yaw]])
            T_true = other.true_pose_at(kb)
            if T_true is not None:
                orow.fix_error_m = float(np.linalg.norm(full[:3] - T_true[:3, 3]))
            if kb < first:
                orow.reason = f"the owner's keyframe {kb} is outside its pose graph's active window"
            else:
                oc = other.anchor if common else (0.0, 0.0)
                s_m = math.hypot(sp.owner_sigma_m, oc[0])
                s_y = math.hypot(sp.owner_sigma_yaw_rad, oc[1])
                g = oloop.graph.gate(kb, tgt, s_m, s_y)
                orow.gate_d2, orow.correction_m = g.d2, float(np.linalg.norm(g.innovation[:3]))
                if not g.accepted:
                    orow.reason = f"fix rejected by the gate (d2 {g.d2:.1f} > {g.threshold:.1f})"
                else:
                    oloop.graph.add_fix(kb, tgt, s_m, s_y)
                    oloop.graph.solve(oloop.config.active_window_m)
                    orow.accepted = True
                    orow.applied_sigma_m = s_m
                    if T_true is not None:
                        orow.applied_error_m = float(np.linalg.norm(tgt[:3] - T_true[:3, 3]))
                    moved.append(other.name)
        if not moved:
            att.reason = (
                f"not informative: weights {sp.rover_weight_m:.2f} (this rover) and "
                f"{sp.owner_weight_m:.2f} ({other.name}) both below {w_min:g}"
            )
            if orow is not None and not orow.reason:
                orow.reason = att.reason
            return False
        ex = Exchange(
            len(ledger), att.time_s, {self.name: kf_rover, other.name: kf_owner}, tuple(moved)
        )
        ledger.append(ex)
        att.exchange = ex.id
        att.accepted = self.name in moved
        if not att.accepted:
            att.reason = (
                f"{other.name} moved (weight {sp.owner_weight_m:.2f}); "
                f"this rover not (weight {sp.rover_weight_m:.2f})"
            )
        if orow is not None:
            orow.exchange = ex.id
            if orow.accepted:
                other.shared_att.append(other._as_attempt(orow, kb, tgt))
        if self.name in moved:
            self.anchor = (att.applied_sigma_m, math.hypot(sp.rover_sigma_yaw_rad, own_common[1]))
            self.last_exchange = ex.id
        if orow is not None and orow.accepted:
            other.anchor = (
                orow.applied_sigma_m,
                math.hypot(sp.owner_sigma_yaw_rad, (other.anchor if common else (0.0, 0.0))[1]),
            )
            other.last_exchange = ex.id
        return att.accepted or (orow is not None and orow.accepted)

    def true_pose_at(self, k: int) -> np.ndarray | None:
        """Ground truth (evaluation only) at keyframe k's tick, or None."""
        f = self.loc.loop.keyframes[k].frame
        for i in range(len(self.ticks) - 1, -1, -1):
            if self.ticks[i][0] == f:
                return self.T_map_rover_true[i]
        return None

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
        ledger: list[Exchange] = []  # the accepted shared registrations (the exchange guard)
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
                    config=cfg,
                    ledger=ledger,
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
