"""Frame sources: what :func:`lunarloc.pipeline.runner.run` plays, one :class:`Frame` at a time.

- :class:`ArchiveSource`: a `.lac` archive played through
  :class:`~lunarloc.io.lac.playback.PlaybackAgent`; odometry from
  :func:`lunarloc.odometry.source.archive_odometry` (visual, IMU or a record), stereo images on the
  frames that have them (each one a keyframe), ground truth for evaluation only.
- :class:`TraverseCsvSource`: a traverse CSV of the LunarLoc dataset (world-frame detections,
  no images, no rover heading) with simulated odometry drift.

A source is a context manager (``with source:`` opens it and computes what it needs before
the first frame, e.g. the archive's odometry) and an iterable of frames. It names itself
(``name``), reports its camera (``camera``, None without images), the site's rocks when it
knows them (``rocks``), the odometry's own per-frame step sigma where it states one
(``step_sigma_m``, {frame: m}, empty when none), the time it spent (``timings``: ``io``,
``odometry``) and a description for the run's configuration (``info()``).

Frames: ``map`` (the reference map's frame, where ground truth lives), ``odo`` (odometry,
equal to ``map`` at the start), ``rover``. Metres, radians, seconds.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lunarloc.core.errors import FileFormatError, InputError
from lunarloc.core.geometry import pose_to_matrix

__all__ = ["Frame", "ArchiveSource", "TraverseCsvSource"]


@dataclass(frozen=True)
class Frame:
    """One frame of a source. Poses are 4x4 transforms ``T_a_b`` (b's pose in a)."""

    frame: int
    time_s: float
    T_odo_rover: np.ndarray  # odometry
    keyframe: bool  # detections (or images to detect in) belong to this frame
    images: Mapping[str, np.ndarray] | None = None  # {camera: grayscale image} (archive sources)
    mounts: Mapping | None = None  # {camera: CameraMount} of those images
    detections_rover: np.ndarray | None = (
        None  # (N, 3) rover-frame detections (sources without images)
    )
    T_map_rover_true: np.ndarray | None = None  # ground truth (evaluation only)


class ArchiveSource:
    """Frames of a `.lac` archive.

    odometry : :class:`lunarloc.config.run.OdometryConfig` (source, IMU and VO settings); its
        ``source`` None means ``visual`` when the archive has front stereo pairs, else ``imu``.
    pairs : stereo pairs whose left camera marks an image frame (the detector's pairs).
    odometry_poses : optional (F, 4, 4) odometry poses ``T_odo_rover``, one per archive frame in
    order,
        replacing the odometry source (to replay the images with another drift).
    max_frames : stop after this many frames.
    """

    def __init__(
        self,
        archive: str | Path,
        odometry=None,
        pairs=None,
        *,
        odometry_poses: np.ndarray | None = None,
        max_frames: int | None = None,
    ):
        from lunarloc.config.run import OdometryConfig
        from lunarloc.perception.camera import STEREO_PAIRS

        self.path = Path(archive)
        self.name = str(archive)
        self.odometry_config = odometry or OdometryConfig()
        self.pairs = tuple(pairs or STEREO_PAIRS)
        self._override = None if odometry_poses is None else np.asarray(odometry_poses, float)
        self.max_frames = max_frames
        self.camera = None
        self.rocks: np.ndarray | None = None
        self.lander_xy: np.ndarray | None = (
            None  # the lander's centre in map (initial.toml), if recorded
        )
        self.odometry_label = ""
        self.step_sigma_m: dict[int, float] = {}  # per frame, the odometry's own step sigma (m)
        self.timings: dict[str, float] = {}
        self._ar = None

    # -------------------------------------------------------------- open / close
    def __enter__(self) -> ArchiveSource:
        from lunarloc.io.lac.archive import LacArchive
        from lunarloc.perception.camera import camera_from_archive
        from lunarloc.pipeline.reference import ROCK_COLUMNS

        t0 = time.perf_counter()
        self._ar = ar = LacArchive(self.path)
        try:
            # the ground truth (evaluation only) finite, or an ArchiveError naming the cell
            ar.poses()
            ar.finite_columns(("mission_time",), "mission time")
            t_odo = time.perf_counter()
            self._odometry = self._odometry_poses(ar)
            self.timings["odometry"] = time.perf_counter() - t_odo
            self.camera = camera_from_archive(ar)
            self._lefts = [l for l, _ in self.pairs if l in ar.cameras]
            if not self._lefts:
                raise FileFormatError(
                    f"{self.path}: no left stereo camera recorded images (have: "
                    f"{', '.join(ar.cameras) or 'none'})"
                )
            self._image_frames = {int(f) for c in self._lefts for f in ar.camera_frames(c)["frame"]}
            if ar.initial.get("lander") is not None:
                self.lander_xy = np.asarray(ar.lander_pose_map()[:2], float)
            if "rocks" in ar.custom_records:
                self.rocks = ar.custom("rocks").to_array(tuple(ROCK_COLUMNS))
        except BaseException:
            self.close()
            raise
        self.timings["io"] = time.perf_counter() - t0 - self.timings["odometry"]
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._ar is not None:
            self._ar.close()
            self._ar = None

    def _odometry_poses(self, ar) -> dict[int, np.ndarray]:
        if self._override is not None:
            if self._override.shape != (len(ar.frame_numbers), 4, 4):
                raise InputError(
                    f"odometry override must be ({len(ar.frame_numbers)}, 4, 4), got "
                    f"{self._override.shape}"
                )
            self.odometry_label = "override"
            return {int(f): r for f, r in zip(ar.frame_numbers, self._override)}
        from lunarloc.odometry.source import archive_odometry, default_odometry_source

        c = self.odometry_config
        traj = archive_odometry(
            ar, c.source or default_odometry_source(ar), imu_config=c.imu, visual_config=c.visual
        )
        self.odometry_label = traj.label
        if traj.step_sigma_m is not None:  # the visual odometry's own step sigmas (m, NaN: none)
            self.step_sigma_m = {int(f): float(v) for f, v in zip(traj.frames, traj.step_sigma_m)}
        return {int(f): T for f, T in zip(traj.frames, traj.T_map_rover)}  # odo == map at the start

    # -------------------------------------------------------------- frames
    @property
    def n_frames(self) -> int:
        n = len(self._ar.frame_numbers)
        return n if self.max_frames is None else min(self.max_frames, n)

    def __iter__(self) -> Iterator[Frame]:
        from lunarloc.io.lac.playback import PlaybackAgent
        from lunarloc.perception.camera import CameraMount

        if self._ar is None:
            raise InputError(f"{self.path}: open the source first (with source: ...)")
        cam, n_total = self.camera, self.n_frames
        t_io = self.timings["io"]
        with PlaybackAgent(self._ar) as agent:
            for n, frame in enumerate(agent, start=1):
                if n > n_total:
                    break
                t0 = time.perf_counter()
                if frame not in self._odometry:
                    raise FileFormatError(f"{self.path}: no odometry pose at frame {frame}")
                gt = agent.get_transform().matrix()
                t = agent.get_mission_time()
                images = mounts = None
                if frame in self._image_frames:
                    images = {
                        k: v
                        for k, v in agent.input_data().get("Grayscale", {}).items()
                        if v is not None
                    }
                    mounts = {
                        name: CameraMount(name, agent.get_camera_position(name).matrix(), cam)
                        for name in images
                    }
                t_io += time.perf_counter() - t0
                self.timings["io"] = t_io
                yield Frame(
                    int(frame),
                    t,
                    self._odometry[frame],
                    images is not None,
                    images,
                    mounts,
                    None,
                    gt,
                )

    def info(self) -> dict:
        """What the run's configuration records about this source."""
        return {
            "archive": self.name,
            "odometry_source": self.odometry_label,
            "camera": None if self.camera is None else asdict(self.camera),
        }


class TraverseCsvSource:
    """Frames of a traverse CSV (world-frame detections, no images) with simulated drift.

    Odometry follows :func:`lunarloc.pipeline.evaluation.drifted_path` (scale error and a heading
    error growing with distance). The CSV has no rover heading, so the "rover" frame here is
    world-aligned at the rover's position: its true yaw is 0, its odometry yaw is the
    accumulated heading error, and a detection's rover-frame offset is ``det - rover``.
    Keyframes are frames with detections, at least ``keyframe_every_s`` apart, plus one at
    least every ``keyframe_max_interval_s``. Frame time is frame number / `rate_hz`.
    """

    def __init__(
        self,
        traverse,
        drift=None,
        rate_hz: float = 20.0,
        keyframe_every_s: float = 0.5,
        keyframe_max_interval_s: float = 2.0,
    ):
        from lunarloc.pipeline.evaluation import DriftModel
        from lunarloc.io.maps import Traverse, load_traverse

        self.traverse: Traverse = (
            traverse if isinstance(traverse, Traverse) else load_traverse(traverse)
        )
        self.name = self.traverse.name
        self.drift = drift or DriftModel(0.05, 0.02)
        self.rate_hz = float(rate_hz)
        self.keyframe_every_s = float(keyframe_every_s)
        self.keyframe_max_interval_s = float(keyframe_max_interval_s)
        self.camera = None
        self.rocks = None
        self.lander_xy = None  # detections of the dataset are already rocks
        self.step_sigma_m: dict[int, float] = {}  # the simulated drift states no per-step sigma
        self.timings: dict[str, float] = {}

    @classmethod
    def for_run(cls, traverse, config) -> TraverseCsvSource:
        """The source a run configuration describes: its odometry drift and rate, and its loop's
        keyframe spacing (``bench loop`` and the loop's NEES benchmark)."""
        return cls(
            traverse,
            config.odometry.drift,
            config.odometry.rate_hz,
            config.loop.keyframe_every_s,
            config.loop.keyframe_max_interval_s,
        )

    def __enter__(self) -> TraverseCsvSource:
        return self

    def __exit__(self, *exc) -> None:
        pass

    @property
    def n_frames(self) -> int:
        return len(self.traverse.frames)

    def __iter__(self) -> Iterator[Frame]:
        from lunarloc.pipeline.evaluation import drifted_path

        trav = self.traverse
        g = trav.rover_xyz
        o, psi = drifted_path(g, self.drift)
        order = np.argsort(trav.detection_frame, kind="stable")
        df = trav.detection_frame[order]
        dx = trav.detections_xyz[order]
        times = trav.frames.astype(float) / self.rate_hz
        last_kf_t = -np.inf
        for i, f in enumerate(trav.frames):
            a, b = np.searchsorted(df, f, "left"), np.searchsorted(df, f, "right")
            t = times[i]
            dets = dx[a:b] - g[i] if b > a else None
            is_kf = (
                dets is not None and t - last_kf_t >= self.keyframe_every_s
            ) or t - last_kf_t >= self.keyframe_max_interval_s
            if is_kf:
                last_kf_t = t
            yield Frame(
                int(f),
                t,
                pose_to_matrix(o[i, 0], o[i, 1], o[i, 2], 0.0, 0.0, psi[i]),
                bool(is_kf),
                detections_rover=(np.zeros((0, 3)) if dets is None else dets.copy())
                if is_kf
                else None,
                T_map_rover_true=pose_to_matrix(g[i, 0], g[i, 1], g[i, 2], 0.0, 0.0, 0.0),
            )

    def info(self) -> dict:
        return {"traverse": self.name, "drift": asdict(self.drift), "rate_hz": self.rate_hz}
