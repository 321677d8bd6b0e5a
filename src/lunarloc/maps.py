"""Landmark maps: the `LandmarkMap` type, its file formats, the public traverse CSV
loader, and aggregation of per-frame rock detections into landmarks.

File formats
------------
* Landmark-map CSV: header ``x,y,z`` with optional ``size`` (m), ``sightings``,
  ``sigma_xy`` and ``sigma_z`` (1-sigma position uncertainty, m) columns, one landmark per row; a first comment line ``# frame: NAME`` keeps the
  frame name.
* Binary: NumPy ``.npz`` with arrays ``positions_xyz``, optional ``sizes``,
  ``sightings``, ``sigma_xy_m`` and ``sigma_z_m``, and a 0-d string ``frame``.
* Traverse CSV (the LunarLoc dataset, ``mit-acl/lunarloc-data``):
  ``frame,x,y,z,detections,boulders`` where ``boulders`` is a Python-literal list
  of ``(x, y, z)`` rock centroids in the map frame.
"""

from __future__ import annotations

import csv
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lunarloc.errors import FileFormatError, InputError
from lunarloc.geometry import as_points, transform_points

log = logging.getLogger(__name__)

__all__ = [
    "LandmarkMap",
    "Traverse",
    "AggregationConfig",
    "aggregate_detections",
    "load_traverse",
    "load_map",
    "save_map",
    "is_traverse_csv",
    "TRAVERSE_COLUMNS",
    "sighting_sigma",
    "NO_HEIGHT_SIGMA_M",
]

TRAVERSE_COLUMNS = ("frame", "x", "y", "z", "detections", "boulders")
#: a landmark's vertical sigma at or above this means "height unknown" (e.g. a rock catalogue
#: without heights): the localizer then associates in 2D + yaw
NO_HEIGHT_SIGMA_M = 1.0e6
_FLOAT = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|nan|inf", re.IGNORECASE)


@dataclass
class LandmarkMap:
    """A set of rock landmarks in one frame.

    Attributes
    ----------
    positions_xyz : (N, 3) landmark centres in metres, in frame `frame`.
    sizes : optional (N,) rock size estimates in metres (diameter-like; same unit in both maps).
    sightings : optional (N,) number of detections (or frames) supporting each landmark.
    frame : name of the frame the positions are expressed in.
    sigma_xy_m : optional (N,) 1-sigma horizontal position uncertainty per axis (m); a grid
        gives its quantisation cell / sqrt(12), an image-built map its sighting spread.
    sigma_z_m : optional (N,) 1-sigma vertical position uncertainty (m).
    Unknown uncertainty stays None: the localizer then uses its configured defaults.
    """

    positions_xyz: np.ndarray
    sizes: np.ndarray | None = None
    sightings: np.ndarray | None = None
    frame: str = "map"
    sigma_xy_m: np.ndarray | None = None
    sigma_z_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.positions_xyz = as_points(self.positions_xyz, "landmark positions")
        n = len(self.positions_xyz)
        for name in ("sizes", "sightings", "sigma_xy_m", "sigma_z_m"):
            val = getattr(self, name)
            if val is None:
                continue
            arr = np.asarray(val, dtype=float).reshape(-1)
            if arr.shape[0] != n:
                raise InputError(f"{name} has {arr.shape[0]} values for {n} landmarks")
            if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise InputError(f"{name} must be finite and non-negative")
            setattr(self, name, arr)

    def __len__(self) -> int:
        return len(self.positions_xyz)

    @property
    def has_heights(self) -> bool:
        """False when the map states that its heights are unknown (NO_HEIGHT_SIGMA_M)."""
        return self.sigma_z_m is None or not bool(np.all(self.sigma_z_m >= NO_HEIGHT_SIGMA_M))

    def subset(self, index) -> "LandmarkMap":
        """Landmarks selected by an index array or boolean mask."""
        idx = np.asarray(index)
        return LandmarkMap(
            self.positions_xyz[idx],
            None if self.sizes is None else self.sizes[idx],
            None if self.sightings is None else self.sightings[idx],
            self.frame,
            None if self.sigma_xy_m is None else self.sigma_xy_m[idx],
            None if self.sigma_z_m is None else self.sigma_z_m[idx],
        )

    def transformed(self, T_new_frame: np.ndarray, frame: str | None = None) -> "LandmarkMap":
        """Copy with positions mapped by `T_new_frame` (4x4) into a new frame."""
        return LandmarkMap(
            transform_points(T_new_frame, self.positions_xyz), self.sizes, self.sightings, frame or self.frame,
            self.sigma_xy_m, self.sigma_z_m,
        )


@dataclass
class Traverse:
    """Per-frame rover positions and rock detections of one traverse.

    Attributes
    ----------
    frames : (F,) frame numbers.
    rover_xyz : (F, 3) rover positions (map frame, m).
    detections_xyz : (D, 3) all rock detections (map frame, m).
    detection_frame : (D,) frame number of each detection.
    name : usually the file stem.
    """

    frames: np.ndarray
    rover_xyz: np.ndarray
    detections_xyz: np.ndarray
    detection_frame: np.ndarray
    name: str = "traverse"

    @property
    def path_length(self) -> float:
        """Length of the rover path in metres."""
        if len(self.rover_xyz) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.rover_xyz, axis=0), axis=1).sum())


# --------------------------------------------------------------------------- traverse CSV


def is_traverse_csv(path: str | Path) -> bool:
    """True if the file's header is the LunarLoc traverse header."""
    with open(path, newline="") as fh:
        header = fh.readline().strip().lower().replace(" ", "")
    return header.split(",")[:6] == list(TRAVERSE_COLUMNS)


def load_traverse(path: str | Path) -> Traverse:
    """Read a LunarLoc traverse CSV (``frame,x,y,z,detections,boulders``).

    Raises FileFormatError naming the file and line for a wrong header, a bad number,
    a malformed boulder list, or a detection count that disagrees with the list.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    frames, rover, dets, det_frame = [], [], [], []
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise FileFormatError(f"{path}: empty file") from None
        header = [h.strip().lower() for h in header]
        if header[:6] != list(TRAVERSE_COLUMNS):
            raise FileFormatError(
                f"{path}:1: expected traverse columns {','.join(TRAVERSE_COLUMNS)}, got {','.join(header)}"
            )
        for row in reader:
            line = reader.line_num
            if not row or (len(row) == 1 and not row[0].strip()):
                continue
            if len(row) != 6:
                raise FileFormatError(f"{path}:{line}: expected 6 fields, got {len(row)}")
            try:
                frame = int(row[0])
                xyz = [float(v) for v in row[1:4]]
                count = int(row[4])
            except ValueError as exc:
                raise FileFormatError(f"{path}:{line}: {exc}") from None
            text = row[5].strip()
            if not (text.startswith("[") and text.endswith("]")):
                raise FileFormatError(f"{path}:{line}: boulders must be a list like [(x, y, z), ...]")
            values = [float(v) for v in _FLOAT.findall(text)]
            if len(values) != 3 * count:
                raise FileFormatError(
                    f"{path}:{line}: detections says {count} but the boulder list has {len(values) / 3:g} points"
                )
            if not np.all(np.isfinite(xyz)) or not np.all(np.isfinite(values)):
                raise FileFormatError(f"{path}:{line}: non-finite value")
            frames.append(frame)
            rover.append(xyz)
            if count:
                dets.append(np.asarray(values).reshape(count, 3))
                det_frame.append(np.full(count, frame))
    if not frames:
        raise FileFormatError(f"{path}: no data rows")
    return Traverse(
        frames=np.asarray(frames, dtype=np.int64),
        rover_xyz=np.asarray(rover, dtype=float),
        detections_xyz=np.concatenate(dets) if dets else np.zeros((0, 3)),
        detection_frame=np.concatenate(det_frame) if det_frame else np.zeros(0, dtype=np.int64),
        name=path.stem,
    )


# --------------------------------------------------------------------------- aggregation


@dataclass(frozen=True)
class AggregationConfig:
    """How per-frame detections become landmarks (one per rock).

    DBSCAN (Ester et al. 1996) groups detections of the same rock; the landmark is
    the component-wise median of its group (robust to stray detections).
    Defaults were chosen by measurement on the 17 real LunarLoc traverses
    (README, "Landmark aggregation").
    """

    radius_m: float = 0.10  # DBSCAN eps: neighbours within this distance belong to one rock
    min_sightings: int = 5  # DBSCAN min_samples: detections needed to make a landmark (drops one-off noise)
    min_frames: int = 2  # a landmark must be seen in at least this many distinct frames

    def __post_init__(self) -> None:
        if not self.radius_m > 0:
            raise InputError("radius_m must be positive")
        if self.min_sightings < 1 or self.min_frames < 1:
            raise InputError("min_sightings and min_frames must be >= 1")


def aggregate_detections(
    detections_xyz: np.ndarray,
    detection_frame: np.ndarray | None = None,
    config: AggregationConfig | None = None,
    frame: str = "map",
) -> LandmarkMap:
    """Cluster detections (D, 3) into a LandmarkMap (median centre, sighting count).

    `detection_frame` (D,) gives the frame of each detection; with it, `sightings`
    counts distinct frames and `config.min_frames` applies.
    """
    from sklearn.cluster import DBSCAN

    cfg = config or AggregationConfig()
    pts = as_points(detections_xyz, "detections")
    if len(pts) == 0:
        return LandmarkMap(np.zeros((0, 3)), sightings=np.zeros(0), frame=frame)
    labels = DBSCAN(eps=cfg.radius_m, min_samples=cfg.min_sightings).fit_predict(pts)
    keep = labels >= 0
    if not np.any(keep):
        return LandmarkMap(np.zeros((0, 3)), sightings=np.zeros(0), frame=frame)
    lab = labels[keep]
    order = np.argsort(lab, kind="stable")
    lab_sorted = lab[order]
    pts_sorted = pts[keep][order]
    starts = np.flatnonzero(np.r_[True, lab_sorted[1:] != lab_sorted[:-1]])
    groups = np.split(np.arange(len(lab_sorted)), starts[1:])
    frames_sorted = None if detection_frame is None else np.asarray(detection_frame)[keep][order]
    centres, counts, spreads = [], [], []
    for g in groups:
        n = len(np.unique(frames_sorted[g])) if frames_sorted is not None else len(g)
        if n < cfg.min_frames and frames_sorted is not None:
            continue
        centres.append(np.median(pts_sorted[g], axis=0))
        counts.append(n)
        spreads.append(sighting_sigma(pts_sorted[g], n))
    if not centres:
        return LandmarkMap(np.zeros((0, 3)), sightings=np.zeros(0), frame=frame)
    sig = np.asarray(spreads, dtype=float).reshape(-1, 2)
    return LandmarkMap(np.asarray(centres), sightings=np.asarray(counts, dtype=float), frame=frame,
                       sigma_xy_m=sig[:, 0], sigma_z_m=sig[:, 1])


def sighting_sigma(points_xyz: np.ndarray, n_independent: int) -> tuple[float, float]:
    """1-sigma (horizontal per axis, vertical) uncertainty of a landmark's median from the
    spread of its sightings: the robust spread (1.4826 x median absolute deviation) over
    sqrt(n_independent) (distinct frames: sightings within a frame share its pose error),
    times 1.25 for the median's efficiency."""
    P = np.asarray(points_xyz, dtype=float)
    mad = 1.4826 * np.median(np.abs(P - np.median(P, axis=0)), axis=0)
    k = 1.25 / np.sqrt(max(int(n_independent), 1))
    return float(k * np.sqrt(0.5 * (mad[0] ** 2 + mad[1] ** 2))), float(k * mad[2])


def traverse_map(traverse: Traverse, config: AggregationConfig | None = None) -> LandmarkMap:
    """Landmark map of a traverse's detections (frame name = traverse name)."""
    return aggregate_detections(traverse.detections_xyz, traverse.detection_frame, config, frame=traverse.name)


__all__.append("traverse_map")


# --------------------------------------------------------------------------- map files


def save_map(landmarks: LandmarkMap, path: str | Path) -> Path:
    """Write a map as CSV (``.csv``) or NumPy binary (``.npz``), chosen by suffix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        extra = {}
        if landmarks.sizes is not None:
            extra["sizes"] = landmarks.sizes
        if landmarks.sightings is not None:
            extra["sightings"] = landmarks.sightings
        for name in _SIGMA_COLUMNS.values():
            if getattr(landmarks, name) is not None:
                extra[name] = getattr(landmarks, name)
        np.savez(path, positions_xyz=landmarks.positions_xyz, frame=np.array(landmarks.frame), **extra)
        return path
    if suffix != ".csv":
        raise InputError(f"{path}: unknown map format '{suffix}' (use .csv or .npz)")
    cols = ["x", "y", "z"]
    data = [landmarks.positions_xyz]
    if landmarks.sizes is not None:
        cols.append("size")
        data.append(landmarks.sizes[:, None])
    if landmarks.sightings is not None:
        cols.append("sightings")
        data.append(landmarks.sightings[:, None])
    for col, name in _SIGMA_COLUMNS.items():
        if getattr(landmarks, name) is not None:
            cols.append(col)
            data.append(getattr(landmarks, name)[:, None])
    table = np.hstack(data) if data else np.zeros((0, 3))
    with open(path, "w", newline="") as fh:
        fh.write(f"# frame: {landmarks.frame}\n")
        fh.write(",".join(cols) + "\n")
        for row in table:
            fh.write(",".join(f"{v:.6f}" for v in row) + "\n")
    return path


# optional per-landmark uncertainty: CSV column -> LandmarkMap attribute (and .npz array)
_SIGMA_COLUMNS = {"sigma_xy": "sigma_xy_m", "sigma_z": "sigma_z_m"}


def _load_map_csv(path: Path) -> LandmarkMap:
    frame = path.stem
    with open(path, newline="") as fh:
        lines = fh.read().splitlines()
    start = 0
    while start < len(lines) and lines[start].startswith("#"):
        m = re.match(r"#\s*frame:\s*(.+)", lines[start])
        if m:
            frame = m.group(1).strip()
        start += 1
    if start >= len(lines):
        raise FileFormatError(f"{path}: no header line")
    header = [h.strip().lower() for h in lines[start].split(",")]
    for required in ("x", "y", "z"):
        if required not in header:
            raise FileFormatError(
                f"{path}:{start + 1}: missing column '{required}' (landmark maps need x,y,z; got {','.join(header)})"
            )
    idx = {name: header.index(name) for name in header}
    rows = []
    for k, line in enumerate(lines[start + 1 :], start=start + 2):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split(",")
        if len(parts) != len(header):
            raise FileFormatError(f"{path}:{k}: expected {len(header)} fields, got {len(parts)}")
        try:
            vals = [float(p) for p in parts]
        except ValueError as exc:
            raise FileFormatError(f"{path}:{k}: {exc}") from None
        if not np.all(np.isfinite(vals)):
            raise FileFormatError(f"{path}:{k}: non-finite value")
        rows.append(vals)
    table = np.asarray(rows, dtype=float).reshape(-1, len(header))
    return LandmarkMap(
        table[:, [idx["x"], idx["y"], idx["z"]]],
        table[:, idx["size"]] if "size" in idx else None,
        table[:, idx["sightings"]] if "sightings" in idx else None,
        frame=frame,
        **{name: table[:, idx[col]] for col, name in _SIGMA_COLUMNS.items() if col in idx},
    )


def load_map(path: str | Path, config: AggregationConfig | None = None) -> LandmarkMap:
    """Load a landmark map from ``.csv``/``.npz``; a traverse CSV is aggregated into one.

    Raises FileFormatError naming the file (and line) when it cannot be read.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                pos = z["positions_xyz"]
                return LandmarkMap(
                    pos,
                    z["sizes"] if "sizes" in z else None,
                    z["sightings"] if "sightings" in z else None,
                    str(z["frame"]) if "frame" in z else path.stem,
                    **{name: z[name] for name in _SIGMA_COLUMNS.values() if name in z},
                )
        except (OSError, ValueError, KeyError) as exc:
            raise FileFormatError(f"{path}: not a lunarloc .npz map ({exc})") from None
    if is_traverse_csv(path):
        return traverse_map(load_traverse(path), config)
    return _load_map_csv(path)
