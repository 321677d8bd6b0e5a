"""Odometry: the rover's motion from what it senses, one Enum of sources.

=================  ===============================================================
source             what it uses
=================  ===============================================================
``record:NAME``    a custom record of the archive (``x,y,z,roll,pitch,yaw`` or
                   ``m00..m33``; see :mod:`lunarloc.odometry.record`)
``imu``            gyro attitude (roll/pitch held by gravity) and ``linear_speed``
                   (:mod:`lunarloc.odometry.imu`)
``visual``         stereo visual odometry on the front pair, IMU between images
                   (:mod:`lunarloc.odometry.visual`)
``ground-truth``   frames.csv's true pose: **evaluation only** (a LAC agent never has it)
=================  ===============================================================

:func:`archive_odometry` gives a pose for *every* frame of an archive, starting at the
archive's initial rover pose (initial.toml ``rover``, the LAC's ``get_initial_position``),
as an :class:`OdometryTrajectory`. Frames: ``map`` (site frame of the ground truth),
``rover`` (x forward, y left, z up). Metres, radians, seconds.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.geometry import invert_transform, matrix_to_pose, pose_to_matrix, yaw_of
from lunarloc.odometry.imu import (
    ImuOdometryConfig,
    imu_odometry,
    imu_samples_from_archive,
    integrate_imu,
    relative_motions,
)

__all__ = [
    "OdometrySource",
    "OdometryTrajectory",
    "parse_odometry_source",
    "default_odometry_source",
    "archive_odometry",
    "ground_truth_poses",
    "odometry_drift",
    "step_errors",
    "FRONT_PAIR",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

FRONT_PAIR = ("FrontLeft", "FrontRight")
DEFAULT_RECORD = "odometry"


class OdometrySource(str, Enum):
    """Where the odometry comes from (``record`` takes a record name: ``record:orbslam``)."""

    RECORD = "record"
    IMU = "imu"
    VISUAL = "visual"
    GROUND_TRUTH = "ground-truth"


@dataclass
class OdometryTrajectory:
    """A pose for every archive frame: ``T_map_rover`` (F, 4, 4) at ``frames`` (F,), ``times_s``
    (F,).

    ``source`` names it (``imu``, ``visual``, ``record:orbslam``, ``ground-truth``);
    ``evaluation_only`` is true for ground truth, which a rover does not have.
    ``measured`` (F,) marks frames whose pose came from the source itself rather than
    from IMU propagation between its samples (all true for ``imu`` and ``ground-truth``).
    """

    frames: np.ndarray
    times_s: np.ndarray
    T_map_rover: np.ndarray
    source: str
    evaluation_only: bool = False
    measured: np.ndarray | None = None
    failures: int = 0  # visual: image pairs where the odometry fell back to the prior
    # visual: per frame, the 1-sigma (m, largest axis) of the visual step ending there, from
    # the step's PnP inliers (StereoVisualOdometry.last_step_covariance); NaN where the frame
    # is not a visual step (IMU-bridged frames, failed pairs, the first pair)
    step_sigma_m: np.ndarray | None = None

    def __len__(self) -> int:
        return int(len(self.frames))

    @property
    def label(self) -> str:
        """The source name, with "(evaluation only)" for ground truth."""
        return f"{self.source} (evaluation only)" if self.evaluation_only else self.source

    def poses6(self) -> np.ndarray:
        """(F, 6) x, y, z, roll, pitch, yaw."""
        return np.array([matrix_to_pose(T) for T in self.T_map_rover], float).reshape(-1, 6)


def parse_odometry_source(text: str | OdometrySource) -> tuple[OdometrySource, str | None]:
    """``"record:orbslam"`` -> (RECORD, "orbslam"); ``"imu"`` -> (IMU, None); ``"record"``
    -> (RECORD, "odometry"). Raises ConfigError listing the choices for anything else."""
    if isinstance(text, OdometrySource):
        return text, (DEFAULT_RECORD if text is OdometrySource.RECORD else None)
    raw = str(text).strip()
    head, sep, name = raw.partition(":")
    try:
        src = OdometrySource(head.strip().lower())
    except ValueError:
        choices = ", ".join(
            ["record:NAME", *(s.value for s in OdometrySource if s is not OdometrySource.RECORD)]
        )
        raise ConfigError(f"unknown odometry source {raw!r}; choose one of {choices}") from None
    if src is OdometrySource.RECORD:
        name = name.strip() if sep else DEFAULT_RECORD
        if not name:
            raise ConfigError("odometry source 'record:' needs a record name, e.g. record:orbslam")
        return src, name
    if sep:
        raise ConfigError(f"odometry source {head!r} takes no ':{name}' suffix")
    return src, None


def _front_pair_frames(archive) -> list[int]:
    left, right = FRONT_PAIR
    if left not in archive.cameras or right not in archive.cameras:
        return []
    a = {
        int(f)
        for f, g in zip(
            archive.camera_frames(left)["frame"], archive.camera_frames(left)["grayscale"]
        )
        if g
    }
    b = {
        int(f)
        for f, g in zip(
            archive.camera_frames(right)["frame"], archive.camera_frames(right)["grayscale"]
        )
        if g
    }
    return sorted(a & b)


def default_odometry_source(archive) -> str:
    """``visual`` when the archive has front stereo pairs, else ``imu`` (what a LAC rover
    senses)."""
    return OdometrySource.VISUAL.value if _front_pair_frames(archive) else OdometrySource.IMU.value


def ground_truth_poses(archive) -> np.ndarray:
    """(F, 4, 4) ``T_map_rover`` from frames.csv (evaluation only)."""
    return (
        np.stack([pose_to_matrix(*p) for p in archive.poses()])
        if archive.n_frames
        else np.zeros((0, 4, 4))
    )


def archive_odometry(
    archive,
    source: str | OdometrySource,
    *,
    progress: Callable[[int, int], None] | None = None,
    imu_config: ImuOdometryConfig | None = None,
    visual_config=None,
) -> OdometryTrajectory:
    """Odometry of every frame of an open :class:`~lunarloc.io.lac.archive.LacArchive` from
    `source`.

    `progress(done, total)` is called as image pairs are processed (``visual``).
    Raises InputError / ArchiveError for data the source cannot use (NaN IMU, a missing or
    malformed record, no front stereo pairs for ``visual``).
    """
    src, name = parse_odometry_source(source)
    if archive.n_frames == 0:
        raise InputError(f"{archive.path}: frames.csv has no rows: no odometry")
    frames = np.asarray(archive.frame_numbers, np.int64)
    times = np.asarray(archive.frames["mission_time"], float)
    if src is OdometrySource.GROUND_TRUTH:
        T = ground_truth_poses(archive)
        return OdometryTrajectory(frames, times, T, src.value, True, np.ones(len(frames), bool))
    T0 = archive.initial_rover_pose()
    if not np.all(np.isfinite(T0)):
        raise InputError(f"{archive.path}: initial.toml 'rover' is not finite")
    if src is OdometrySource.IMU:
        _, T = imu_odometry(archive, imu_config)
        return OdometryTrajectory(frames, times, T, src.value, False, np.ones(len(frames), bool))

    # record and visual: measured poses at some frames, IMU in between
    def imu_poses() -> np.ndarray:
        return integrate_imu(imu_samples_from_archive(archive), T0, imu_config)

    def imu_rel() -> np.ndarray:
        return relative_motions(imu_poses())

    if src is OdometrySource.RECORD:
        from lunarloc.odometry.record import read_record_poses

        rec_frames, T_rec = read_record_poses(archive, name)
        index = {int(f): i for i, f in enumerate(frames)}
        missing = [int(f) for f in rec_frames if int(f) not in index]
        if missing:
            logger.warning(
                "%s: record %s has %d frame(s) not in frames.csv (first %d); ignored",
                archive.path,
                name,
                len(missing),
                missing[0],
            )
        keep = [i for i, f in enumerate(rec_frames) if int(f) in index]
        if not keep:
            raise InputError(f"{archive.path}: custom/{name}.csv shares no frame with frames.csv")
        rec_frames, T_rec = rec_frames[keep], T_rec[keep]
        measured = {index[int(f)]: T for f, T in zip(rec_frames, T_rec)}
        # a record with every frame needs no IMU (nor a clean IMU column)
        rel = (
            imu_rel()
            if len(measured) < len(frames)
            else np.tile(np.eye(4), (len(frames) - 1, 1, 1))
        )
        T = _bridge(len(frames), T0, rel, measured)
        mask = np.zeros(len(frames), bool)
        mask[list(measured)] = True
        return OdometryTrajectory(frames, times, T, f"record:{name}", False, mask)
    # IMU once the pairs are known
    return _visual(archive, frames, times, T0, imu_poses, progress, visual_config)


def _bridge(
    n: int, T0: np.ndarray, imu_rel: np.ndarray, measured: dict[int, np.ndarray]
) -> np.ndarray:
    """Per-frame poses: IMU propagation from `T0` up to the first measured frame, whose
    measured pose anchors the measurement frame there (``T_map_meas``); later measured
    frames are ``T_map_meas @ T_meas_rover``, frames in between propagate the last pose."""
    out = np.empty((n, 4, 4))
    out[0] = T0
    T_map_meas = None
    for i in range(n):
        if i > 0:
            out[i] = out[i - 1] @ imu_rel[i - 1]
        if i in measured:
            if T_map_meas is None:
                T_map_meas = out[i] @ invert_transform(measured[i])
            out[i] = T_map_meas @ measured[i]
    return out


def _visual(archive, frames, times, T0, imu_poses, progress, visual_config) -> OdometryTrajectory:
    pair_frames = _front_pair_frames(archive)
    if not pair_frames:
        raise InputError(
            f"{archive.path}: no frame has both {FRONT_PAIR[0]} and {FRONT_PAIR[1]} images: "
            "visual odometry needs the front stereo pair (use --odometry imu)"
        )
    from lunarloc.odometry.tilt import GravityAlignedChain
    from lunarloc.odometry.visual import StereoVisualOdometry, VisualOdometryConfig
    from lunarloc.perception.camera import camera_from_archive, mounts_from_archive_row

    T_imu = imu_poses()
    imu_rel = relative_motions(T_imu)
    chain = GravityAlignedChain((visual_config or VisualOdometryConfig()).gravity_tilt_gain)

    camera = camera_from_archive(archive)
    # camera body poses from the first pair's rows (the IPEx rig where a row has none), as
    # optical-frame mounts (OpenCV axes), which the visual odometry takes
    rows = {cam: archive.camera_row(cam, pair_frames[0]) for cam in FRONT_PAIR}
    mounts = mounts_from_archive_row(rows, camera)
    vo = StereoVisualOdometry(
        camera,
        mounts[FRONT_PAIR[0]].T_rover_optical,
        mounts[FRONT_PAIR[1]].T_rover_optical,
        visual_config,
    )
    index = {int(f): i for i, f in enumerate(frames)}
    pair_idx = sorted(index[f] for f in pair_frames if f in index)
    n = len(frames)
    out = np.empty((n, 4, 4))
    measured = np.zeros(n, bool)
    step_sigma_m = np.full(n, np.nan)
    last = None
    failures = 0
    k_next = 0
    for i in range(n):
        out[i] = T0 if i == 0 else out[i - 1] @ imu_rel[i - 1]
        if k_next < len(pair_idx) and pair_idx[k_next] == i:
            k_next += 1
            f = int(frames[i])
            imgs = archive.read_images([(c, f, "grayscale") for c in FRONT_PAIR])
            left, right = (imgs[(c, f, "grayscale")] for c in FRONT_PAIR)
            prior = None if last is None else invert_transform(out[last]) @ out[i]
            T_odo_rover = vo.update(left, right, prior)
            # visual motion chained from the first pair's IMU-propagated pose, roll and pitch from
            # gravity
            out[i] = chain.add(T_odo_rover, T_imu[i], out[i])
            measured[i] = True
            failures += 0 if getattr(vo, "last_ok", True) else 1
            C = getattr(vo, "last_step_covariance", None)
            if C is not None:
                step_sigma_m[i] = float(np.sqrt(max(np.linalg.eigvalsh(C[:3, :3])[-1], 0.0)))
            last = i
            if progress is not None:
                progress(k_next, len(pair_idx))
    return OdometryTrajectory(
        frames, times, out, OdometrySource.VISUAL.value, False, measured, failures, step_sigma_m
    )


def odometry_drift(T_est: np.ndarray, T_gt: np.ndarray) -> dict:
    """Drift of an odometry trajectory against ground truth (both (F, 4, 4), same frames).

    ``final_error_m`` and ``final_error_pct`` (of the true path length), ``rmse_m``
    (3D position, no alignment: both start at the same pose), ``heading_error_deg``
    (final, wrapped) and ``heading_deg_per_m``; ``max_heading_error_deg`` over the run.
    """
    E, G = np.asarray(T_est, float), np.asarray(T_gt, float)
    if E.shape != G.shape or E.ndim != 3 or len(E) == 0:
        raise InputError(
            f"trajectories must be (F, 4, 4) of equal length, got {E.shape} and {G.shape}"
        )
    pe, pg = E[:, :3, 3], G[:, :3, 3]
    path = float(np.linalg.norm(np.diff(pg, axis=0), axis=1).sum()) if len(pg) > 1 else 0.0
    err = np.linalg.norm(pe - pg, axis=1)
    dyaw = np.array([yaw_of(e[:3, :3]) - yaw_of(g[:3, :3]) for e, g in zip(E, G)])
    dyaw = np.degrees(np.abs((dyaw + math.pi) % (2 * math.pi) - math.pi))
    final = float(err[-1])
    return {
        "frames": int(len(E)),
        "path_length_m": round(path, 4),
        "final_error_m": round(final, 4),
        "final_error_pct": round(100.0 * final / path, 3) if path > 0 else None,
        "rmse_m": round(float(np.sqrt(np.mean(err**2))), 4),
        "max_error_m": round(float(err.max()), 4),
        "heading_error_deg": round(float(dyaw[-1]), 4),
        "heading_deg_per_m": round(float(dyaw[-1]) / path, 5) if path > 0 else None,
        "max_heading_error_deg": round(float(dyaw.max()), 4),
    }


def step_errors(T_est: np.ndarray, T_gt: np.ndarray) -> dict:
    """Errors of the motion between consecutive poses (both (F, 4, 4), same frames; pass the
    measured frames only to score each visual step): the step's translation against the true
    step's (3D and horizontal, each in its own previous rover frame, cm) and its yaw change
    against the true one (degrees), as p50 / p95 / max, and the number of steps over 2 cm."""
    E, G = np.asarray(T_est, float), np.asarray(T_gt, float)
    if E.shape != G.shape or E.ndim != 3 or len(E) < 2:
        raise InputError(
            f"trajectories must be (F, 4, 4) of equal length F >= 2, got {E.shape} and {G.shape}"
        )
    SE = np.einsum("nji,njk->nik", E[:-1, :3, :3], E[1:, :3, 3:] - E[:-1, :3, 3:])[..., 0]
    SG = np.einsum("nji,njk->nik", G[:-1, :3, :3], G[1:, :3, 3:] - G[:-1, :3, 3:])[..., 0]
    d = 100.0 * (SE - SG)
    e3, eh = np.linalg.norm(d, axis=1), np.linalg.norm(d[:, :2], axis=1)

    def dyaw(T):
        return np.diff(np.unwrap([yaw_of(R) for R in T[:, :3, :3]]))

    ey = np.degrees(np.abs(dyaw(E) - dyaw(G)))
    out = {"steps": int(len(d)), "steps_over_2cm": int(np.sum(e3 > 2.0))}
    for name, x in (("step_cm", e3), ("step_horizontal_cm", eh), ("step_yaw_deg", ey)):
        for q, v in zip(("p50", "p95", "max"), np.percentile(x, [50, 95, 100])):
            out[f"{name}_{q}"] = round(float(v), 3)
    return out
