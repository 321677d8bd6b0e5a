"""The pipelines behind the commands: :func:`run` (online localization over a whole
traverse) and :func:`detect` (rock detections of an archive to a traverse CSV).

``run(source, reference, config)`` reads like its table of contents:

1. open the frame **source** (:mod:`lunarloc.pipeline.sources`: a `.lac` archive or a traverse CSV),
   which computes its odometry;
2. for each frame: **detection** of rocks in its stereo images (rover frame,
   :class:`~lunarloc.perception.detector.Detector`) when it has images, else the
   detections the source gives;
3. the **loop state** (:class:`lunarloc.online.loop.LoopState`) takes the frame: local map,
   association with the reference, gated fixes in the pose graph;
4. at the end, the final pose-graph solve and the :class:`~lunarloc.online.loop.LoopResult`, which
   :func:`lunarloc.io.runs.write_run` writes as a run folder.

The per-tick component an agent calls is :class:`lunarloc.online.component.OnlineLocalizer`; this is
the whole-traverse driver (kiss-icp's ``OdometryPipeline.run()`` to its ``register_frame``).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from lunarloc.config.run import RunConfig
from lunarloc.core.errors import InputError, import_cv2
from lunarloc.online.loop import LoopResult, LoopState
from lunarloc.io.maps import LandmarkMap
from lunarloc.mapping.lac_map import LANDER_EXCLUSION_M

__all__ = ["run", "detect", "DetectResult", "add_to_mapper", "place_mapper", "LANDER_EXCLUSION_M"]


def run(
    source,
    reference: LandmarkMap,
    config: RunConfig | None = None,
    *,
    progress: Callable[[int, int], None] | None = None,
    mapper=None,
) -> LoopResult:
    """Online localization of every frame of `source`
    (:class:`~lunarloc.pipeline.sources.ArchiveSource`
    or :class:`~lunarloc.pipeline.sources.TraverseCsvSource`) against `reference` (frame ``map``).

    config : :class:`RunConfig` (default: ``RunConfig()``, the settings for images); the
        detector is scaled to the source's image width. `progress(done, total)` per frame.
    mapper : optional :class:`~lunarloc.mapping.lac_map.LacMapper`: every image frame's stereo
        points and detections are added to it (the lander excluded), and at the end every frame
        is re-placed with the corrected poses (``LoopResult.T_map_rover``): ``mapper.grid()``
        is then the LAC map of the run (:func:`place_mapper` re-places it with other poses)."""
    cfg = config or RunConfig()
    loop = LoopState(reference, cfg.loop, cfg.localization)
    with source:
        loop.set_odometry(odometry_of(source))  # its windows state this odometry's bounds
        detector = _detector(source, cfg)
        if mapper is not None and source.lander_xy is not None:
            mapper.exclude_disc(source.lander_xy, LANDER_EXCLUSION_M)
        example = _ExampleFrame()
        step_sigma = source.step_sigma_m  # the odometry's own, per frame (empty: none)
        total, n_kf = source.n_frames, 0
        for n, frame in enumerate(source, start=1):
            detections = frame.detections_rover
            if frame.images is not None:
                t0 = time.perf_counter()
                fd = detector.detect_frame(
                    frame.images, frame.mounts, None, frame.frame, keep_depth=mapper is not None
                )
                loop.timings["detection"] += time.perf_counter() - t0
                if mapper is not None:
                    t0 = time.perf_counter()
                    add_to_mapper(
                        mapper, frame.frame, frame.T_odo_rover, fd, detector, frame.images
                    )
                    loop.timings["lac_map"] = (
                        loop.timings.get("lac_map", 0.0) + time.perf_counter() - t0
                    )
                detections = np.array([d.p_rover for d in fd.detections], float).reshape(-1, 3)
                if source.lander_xy is not None:  # the lander is no rock: drop detections on it
                    from lunarloc.perception.detector import on_lander

                    detections = detections[
                        ~on_lander(detections, frame.T_odo_rover, source.lander_xy)
                    ]
                example.offer(fd, frame, source.camera)
            n_kf += frame.keyframe
            loop.step(
                frame.frame,
                frame.time_s,
                frame.T_odo_rover,
                detections,
                frame.T_map_rover_true,
                keyframe=frame.keyframe,
                odometry_step_sigma_m=step_sigma.get(frame.frame),
            )
            if progress:
                progress(n, total)
    if n_kf == 0:
        raise InputError(f"{source.name}: no image frames were played; nothing to localize")
    loop.timings.update(source.timings)
    info = source.info()
    if detector is not None:
        info["detector_scaled"] = detector.config.to_dict()
    result = loop.finish(
        n_kf, source.name, source.rocks, example.best, {**cfg.to_dict(), "info": info}
    )
    if mapper is not None:
        place_mapper(mapper, result.frames, result.T_map_rover)
    return result


def add_to_mapper(mapper, frame_id, T_map_rover, fd, detector, images) -> None:
    """Add one frame's detections (:class:`~lunarloc.perception.detector.FrameDetections`,
    detected with ``keep_depth=True``) and its pairs' stereo points to `mapper`
    (:func:`lunarloc.mapping.lac_map.frame_inputs`)."""
    from lunarloc.mapping.lac_map import frame_inputs

    points, rocks = frame_inputs(fd, detector, images)
    mapper.add_frame(frame_id, T_map_rover, points, rocks)


def place_mapper(mapper, frames, T_map_rover) -> int:
    """Re-place every frame `mapper` holds with its pose in `T_map_rover` ((F, 4, 4), one per
    entry of `frames`). Returns the number of frames moved."""
    index = {int(f): k for k, f in enumerate(np.asarray(frames).tolist())}
    moved = 0
    for fid in mapper.frame_ids:
        k = index.get(int(fid))
        if k is not None:
            moved += mapper.repose(fid, T_map_rover[k])
    return moved


def odometry_of(source):
    """What the loop needs to know of `source`'s odometry to state its windows' distortion
    (:meth:`lunarloc.online.loop.LoopState.set_odometry`): a traverse CSV's simulated drift,
    exactly,
    as bounds; an archive's odometry source label (``visual``, ``record:NAME``, ...)."""
    from lunarloc.online.loop import OdometryBounds

    drift = getattr(source, "drift", None)
    if drift is not None:
        return OdometryBounds(
            abs(float(drift.scale_error)), abs(float(drift.heading_drift_deg_per_m))
        )
    return getattr(source, "odometry_label", None) or None


def _detector(source, cfg: RunConfig):
    """The detector for the source's camera (None for sources without images)."""
    if source.camera is None:
        return None
    from lunarloc.perception.detector import Detector

    return Detector(cfg.detector_for(source.camera.width), source.camera)


class _ExampleFrame:
    """The image frame with the most detections, kept for the run's camera-frame figure."""

    def __init__(self):
        self.best: dict | None = None

    def offer(self, fd, frame, camera) -> None:
        dets = fd.detections
        if not dets or (self.best is not None and len(dets) <= self.best["n"]):
            return
        left = fd.pairs[0].camera if fd.pairs else next(iter(frame.images))
        on = [d for d in dets if d.camera == left]
        self.best = {
            "n": len(dets),
            "frame": int(frame.frame),
            "camera": left,
            "image": frame.images[left],
            "uv": np.array([d.uv for d in on], float).reshape(-1, 2),
            "radius_px": np.array([d.radius_m / d.depth_m * camera.fx for d in on]),
            "depth_m": np.array([d.depth_m for d in on]),
        }


# --------------------------------------------------------------------------- detection only


@dataclass
class DetectResult:
    """What :func:`detect` did: rows written, detections, seconds per stage (totals)."""

    output: Path
    frames: int
    detections: int
    pose_label: str  # what placed the detections in the map frame
    stage_seconds: dict[str, float] = field(default_factory=dict)
    wall_s: float = 0.0

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else 0.0

    def per_frame_s(self) -> dict[str, float]:
        return {k: v / max(self.frames, 1) for k, v in self.stage_seconds.items()}


def _rover_xyz(fd) -> np.ndarray:
    """The rover position of a frame's pose; InputError where the frame has none."""
    if fd.T_map_rover is None:
        raise InputError(f"frame {fd.frame} has no rover pose: cannot write map-frame boulders")
    if not np.all(np.isfinite(fd.T_map_rover)):
        raise InputError(
            f"frame {fd.frame}: the rover pose is not finite (NaN in frames.csv or odometry)"
        )
    return fd.T_map_rover[:3, 3]


def detect(
    archive: str | Path,
    output: str | Path,
    config: RunConfig | None = None,
    *,
    pose: str = "ground-truth",
    every: int = 1,
    debug_dir: str | Path | None = None,
    lander_xy=None,
    progress: Callable[[int, int, int], None] | None = None,
) -> DetectResult:
    """Detect rocks in every `every`-th stereo frame of `archive` and write the traverse CSV
    `output` (``frame,x,y,z,detections,boulders``) and its configuration
    (``OUTPUT.config.json``: the :class:`RunConfig` and an ``info`` section).

    pose : ``ground-truth`` or ``odometry`` (the archive's odometry record) places the
        detections; ``config.odometry.source``, when set, places them with that odometry
        source instead. `progress(done, total, detections)` per frame."""
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.io.outputs import atomic_open
    from lunarloc.io.maps import PoseProvenance, save_traverse
    from lunarloc.perception.detector import (
        Detector,
        PoseSource,
        debug_overlay,
        detect_archive,
    )
    from lunarloc.io.runs import to_json_ready
    from lunarloc.perception.camera import camera_from_archive

    cfg = config or RunConfig()
    pose_src = PoseSource(pose)
    output = Path(output)
    t_start = time.perf_counter()
    with LacArchive(archive) as ar:
        camera = camera_from_archive(ar)
        det_cfg = cfg.detector_for(camera.width)
        detector = Detector(det_cfg, camera)  # fails early (e.g. missing weights)
        lefts = [left for left, _ in det_cfg.pairs]
        frames = sorted(
            {
                int(f)
                for f in ar.frame_numbers
                for c in lefts
                if c in ar.cameras and ar.camera_row(c, int(f))
            }
        )[::every]
        res = DetectResult(output, 0, 0, pose_src.value)
        poses = None
        if cfg.odometry.source is not None:
            from lunarloc.odometry.source import archive_odometry

            o = cfg.odometry
            traj = archive_odometry(ar, o.source, imu_config=o.imu, visual_config=o.visual)
            poses = dict(zip(traj.frames.tolist(), traj.T_map_rover))
            res.pose_label = traj.label
            res.stage_seconds["odometry"] = time.perf_counter() - t_start
        elif pose_src is PoseSource.ODOMETRY:  # the archive's own odometry record
            from lunarloc.odometry.source import archive_odometry

            if "odometry" not in ar.custom_records:
                raise InputError(
                    f"{ar.path}: no odometry record; use --pose ground-truth or --odometry SOURCE"
                )
            traj = archive_odometry(ar, "record:odometry")
            poses = dict(zip(traj.frames.tolist(), traj.T_map_rover))

        def frames_iter():
            for fd in detect_archive(
                ar,
                det_cfg,
                pose_src,
                detector=detector,
                frames=frames,
                keep_depth=debug_dir is not None,
                poses=poses,
                lander_xy=lander_xy,
            ):
                res.detections += len(fd.detections)
                for k, v in fd.timings.items():
                    res.stage_seconds[k] = res.stage_seconds.get(k, 0.0) + v
                if debug_dir is not None:
                    cv2 = import_cv2()
                    for pair in fd.pairs:
                        img = ar.grayscale(pair.camera, fd.frame)
                        cv2.imwrite(
                            str(Path(debug_dir) / f"{pair.camera}_{fd.frame:06d}.png"),
                            debug_overlay(img, pair),
                        )
                if progress:
                    progress(res.frames + 1, len(frames), res.detections)
                res.frames += 1
                yield fd

        # the pose provenance in every row (the dataset's schema plus a 'pose' column): a file
        # placed by odometry is judged with the odometry prior, one placed by ground truth rigid
        provenance = PoseProvenance.from_label(
            "record:odometry" if res.pose_label == PoseSource.ODOMETRY.value else res.pose_label
        )
        n = save_traverse(
            output,
            ((fd.frame, _rover_xyz(fd), fd.positions_map()) for fd in frames_iter()),
            provenance,
        )
    res.frames = n
    res.wall_s = time.perf_counter() - t_start
    info = {"archive": str(archive), "pose": res.pose_label, "detector_scaled": det_cfg.to_dict()}
    with atomic_open(output.with_suffix(output.suffix + ".config.json"), "w") as fh:
        fh.write(json.dumps(to_json_ready({**cfg.to_dict(), "info": info}), indent=2, default=str))
    return res
