"""Landmark maps: the `LandmarkMap` type, its file formats, the public traverse CSV
loader, and aggregation of per-frame rock detections into landmarks.

File formats
------------
* Landmark-map CSV: header ``x,y,z`` with optional ``size`` (m), ``sightings``,
  ``sigma_xy`` and ``sigma_z`` (1-sigma position uncertainty, m) columns, and optional
  ``sighting_arc``, ``sighting_arc_min`` and ``sighting_arc_max`` (m: where along the vehicle's
  odometry path the landmark was seen from, all three or none), one landmark per row; a first
  comment line ``# frame: NAME`` keeps the frame name. Files without the optional columns load.
* Binary: NumPy ``.npz`` with arrays ``positions_xyz``, optional ``sizes``,
  ``sightings``, ``sigma_xy_m``, ``sigma_z_m``, ``sighting_arc_m``, ``sighting_arc_min_m`` and
  ``sighting_arc_max_m``, and 0-d strings ``frame`` and ``pose_provenance``.
* Traverse CSV (the LunarLoc dataset, ``mit-acl/lunarloc-data``):
  ``frame,x,y,z,detections,boulders`` where ``boulders`` is a Python-literal list
  of ``(x, y, z)`` rock centroids in the map frame. The dataset's files are posed by ground truth
  (its README); lunarloc's writers (:func:`save_traverse`) add a seventh column ``pose`` (the
  pose provenance, :class:`PoseProvenance`), which readers by column name (pandas) ignore.
"""

from __future__ import annotations

import csv
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lunarloc.core.errors import FileFormatError, InputError, LimitError
from lunarloc.core.geometry import as_points, transform_points
from lunarloc.io import inputs as _inputs

log = logging.getLogger(__name__)

__all__ = [
    "LandmarkMap",
    "ROCK_COLUMNS",
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
    "path_arc_length_m",
    "detection_arcs_m",
    "PoseProvenance",
    "save_traverse",
    "format_boulders",
]

TRAVERSE_COLUMNS = ("frame", "x", "y", "z", "detections", "boulders")
#: the optional seventh traverse column: each row's pose provenance (:class:`PoseProvenance`)
POSE_COLUMN = "pose"
# The boulders field: a Python-literal list of 3-tuples of plain decimal numbers, nothing else
# (no names, calls, dicts, nesting, underscores, nan/inf). Checked as a whole by one regular
# expression (no recursion, linear time), then the numbers are read.
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_VAL = rf"(?:{_NUM}|[-+]?(?:nan|inf))"  # nan/inf are read, then refused as non-finite
_NUMBER = re.compile(_VAL, re.IGNORECASE)
_TUPLE = rf"\(\s*{_VAL}\s*,\s*{_VAL}\s*,\s*{_VAL}\s*,?\s*\)"
_BOULDERS = re.compile(rf"\[\s*(?:{_TUPLE}(?:\s*,\s*{_TUPLE})*\s*,?\s*)?\]", re.IGNORECASE)


# --------------------------------------------------------------------------- pose provenance

#: the poses that placed a map's detections: the vehicle's ground truth (a rigid map) or odometry
POSE_GROUND_TRUTH = "ground-truth"
POSE_ODOMETRY = "odometry"
_POSE_DETAIL = r"[A-Za-z0-9_.:() +-]{1,80}"  # a source's name: no comma, quote or line break
_POSE_TEXT = re.compile(rf"(ground-truth|odometry)(?::({_POSE_DETAIL}))?")


@dataclass(frozen=True)
class PoseProvenance:
    """Which poses placed a vehicle map's detections, and who says so.

    ``poses``: ``"ground-truth"`` (the vehicle's true poses: the map is rigid, its odometry
    distortion bounds are 0) or ``"odometry"`` (a drifting estimate: the localizer keeps its
    prior of real rover odometry). ``detail``: the source's name (``visual``, ``record:odometry``,
    ``corrected by the loop``; at most 80 letters, digits, spaces and ``_.:()+-``), may be empty.
    ``stated_by``: where it was read (the
    file's ``pose`` column, its ``# pose:`` line, the detect command's ``.config.json`` beside it)
    or, for a dataset traverse CSV that states none, that its schema says so.

    In a file it is written as ``POSES`` or ``POSES:DETAIL`` (:meth:`to_text`)."""

    poses: str
    detail: str = ""
    stated_by: str = ""

    def __post_init__(self) -> None:
        if self.poses not in (POSE_GROUND_TRUTH, POSE_ODOMETRY):
            raise InputError(
                f"pose provenance must be {POSE_GROUND_TRUTH!r} or {POSE_ODOMETRY!r}, got "
                f"{self.poses!r}"
            )
        if self.detail and (
            not re.fullmatch(_POSE_DETAIL, self.detail) or self.detail != self.detail.strip()
        ):
            raise InputError(
                f"pose provenance detail {self.detail[:60]!r}: at most 80 letters, digits, inner "
                "spaces and _.:()+- (it is written into CSV rows and comment lines)"
            )

    @property
    def rigid(self) -> bool:
        """Whether the poses were the ground truth (the map is rigid)."""
        return self.poses == POSE_GROUND_TRUTH

    def to_text(self) -> str:
        """``ground-truth`` or ``odometry[:DETAIL]``: what a file holds."""
        return self.poses + (f":{self.detail}" if self.detail else "")

    @classmethod
    def parse(cls, text: str, stated_by: str = "") -> "PoseProvenance":
        """The provenance written as :meth:`to_text` gives it; InputError for anything else."""
        m = _POSE_TEXT.fullmatch(text.strip())
        if not m:
            raise InputError(
                "pose provenance must be 'ground-truth' or 'odometry[:SOURCE]', got "
                f"{text.strip()[:60]!r}"
            )
        return cls(m.group(1), m.group(2) or "", stated_by)

    @classmethod
    def from_label(cls, label: str, stated_by: str = "") -> "PoseProvenance":
        """From the name of the poses' source as lunarloc's detect and odometry sources give it
        (``ground-truth``, ``ground-truth (evaluation only)``, ``odometry``, ``visual``,
        ``record:orbslam``): ground truth for ``ground-truth...``, else odometry from that
        source."""
        label = str(label).strip()
        if label.startswith(POSE_GROUND_TRUTH):
            return cls(POSE_GROUND_TRUTH, "", stated_by)
        detail = re.sub(r"[^A-Za-z0-9_.:() +-]", "", label)[:80].strip()
        return cls(POSE_ODOMETRY, "" if detail == POSE_ODOMETRY else detail, stated_by)

    def describe(self) -> str:
        """One phrase: ``ground truth (the file's pose column)``."""
        what = "ground truth" if self.rigid else "odometry"
        if self.detail:
            what += f" {self.detail}"
        return what + (f" ({self.stated_by})" if self.stated_by else "")

    def to_dict(self) -> dict:
        return {"poses": self.poses, "detail": self.detail, "stated_by": self.stated_by}


ROCK_COLUMNS = [
    "id",
    "x",
    "y",
    "z",
    "radius",
]  # a rock list CSV (simulated sites, the LAC rock catalogue)


def parse_boulders(text: str) -> np.ndarray:
    """(N, 3) float array from a boulders field ``[(x, y, z), ...]`` (the LunarLoc dataset
    format). Anything else (other nesting, names, dicts, ``1_000``, tuples of 2 or 4) raises
    ValueError; the caller adds file and line. Values may still be non-finite (``1e999``)."""
    t = text.strip()
    if len(t) > _inputs.MAX_CSV_FIELD_CHARS:
        raise ValueError(f"boulders field longer than {_inputs.MAX_CSV_FIELD_CHARS:,} characters")
    if not _BOULDERS.fullmatch(t):
        raise ValueError("boulders must be a list like [(x, y, z), ...] of plain numbers")
    vals = np.array(_NUMBER.findall(t), dtype=float)
    return vals.reshape(-1, 3)


#: LandmarkMap's optional sighting arc-length fields (all three or none)
_ARC_FIELDS = ("sighting_arc_m", "sighting_arc_min_m", "sighting_arc_max_m")

#: a landmark's vertical sigma at or above this means "height unknown" (e.g. a rock catalogue
#: without heights): the localizer then associates in 2D + yaw
NO_HEIGHT_SIGMA_M = 1.0e6


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
    sighting_arc_m, sighting_arc_min_m, sighting_arc_max_m : optional (N,) where the vehicle
        saw each landmark from, as distance travelled (horizontally, m) along its odometry path
        from that path's first pose (:func:`path_arc_length_m`): the mean over the landmark's
        detections, and their least and greatest. All three or none; None for maps not built
        by a vehicle (overhead grids, catalogues). The localizer's bend model
        (:func:`lunarloc.localization.bending.bending_fit`) places each landmark there along the
        path it is
        given (``localize(path_xyz=)``, the same path from the same first pose); a wide span
        (min to max) marks a landmark the path passed more than once.
    pose_provenance : optional :class:`PoseProvenance`, which poses placed the landmarks (read
        from the file by :func:`load_map` / :func:`load_vehicle`). Ground truth makes
        :func:`lunarloc.localize` judge the map rigid where no odometry bounds are stated; None
        (unknown) or odometry keep its prior of real rover odometry. Kept by :meth:`subset` and
        :meth:`transformed` (a rigid motion keeps a map rigid).
    """

    positions_xyz: np.ndarray
    sizes: np.ndarray | None = None
    sightings: np.ndarray | None = None
    frame: str = "map"
    sigma_xy_m: np.ndarray | None = None
    sigma_z_m: np.ndarray | None = None
    sighting_arc_m: np.ndarray | None = None
    sighting_arc_min_m: np.ndarray | None = None
    sighting_arc_max_m: np.ndarray | None = None
    pose_provenance: PoseProvenance | None = None

    def __post_init__(self) -> None:
        if self.pose_provenance is not None and not isinstance(
            self.pose_provenance, PoseProvenance
        ):
            raise InputError(
                "pose_provenance must be a PoseProvenance or None, got "
                f"{type(self.pose_provenance).__name__}"
            )
        self.positions_xyz = as_points(self.positions_xyz, "landmark positions")
        _check_coordinates(self.positions_xyz, "landmark positions")
        n = len(self.positions_xyz)
        for name in ("sizes", "sightings", "sigma_xy_m", "sigma_z_m") + _ARC_FIELDS:
            val = getattr(self, name)
            if val is None:
                continue
            arr = np.asarray(val, dtype=float).reshape(-1)
            if arr.shape[0] != n:
                raise InputError(f"{name} has {arr.shape[0]} values for {n} landmarks")
            if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise InputError(f"{name} must be finite and non-negative")
            setattr(self, name, arr)
        given = [getattr(self, name) is not None for name in _ARC_FIELDS]
        if any(given) and not all(given):
            raise InputError(f"{', '.join(_ARC_FIELDS)} go together: give all three or none")
        if all(given) and not np.all(
            (self.sighting_arc_min_m <= self.sighting_arc_m + 1e-5)
            & (self.sighting_arc_m <= self.sighting_arc_max_m + 1e-5)
        ):
            raise InputError(
                "sighting arc lengths must satisfy min <= mean <= max for every landmark"
            )

    @property
    def has_sighting_arcs(self) -> bool:
        """Whether the map says where along its vehicle's path each landmark was seen from."""
        return self.sighting_arc_m is not None

    def _arcs(self, idx=None) -> dict:
        return {
            name: (
                None
                if getattr(self, name) is None
                else getattr(self, name)
                if idx is None
                else getattr(self, name)[idx]
            )
            for name in _ARC_FIELDS
        }

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
            **self._arcs(idx),
            pose_provenance=self.pose_provenance,
        )

    def transformed(self, T_new_frame: np.ndarray, frame: str | None = None) -> "LandmarkMap":
        """Copy with positions mapped by `T_new_frame` (4x4) into a new frame."""
        return LandmarkMap(
            transform_points(T_new_frame, self.positions_xyz),
            self.sizes,
            self.sightings,
            frame or self.frame,
            self.sigma_xy_m,
            self.sigma_z_m,
            **self._arcs(),
            pose_provenance=self.pose_provenance,
        )


def _check_coordinates(xyz: np.ndarray, name: str) -> None:
    """Refuse absurd coordinates (beyond +-MAX_ABS_COORD_M): they overflow distance sums."""
    if xyz.size and float(np.max(np.abs(xyz))) > _inputs.MAX_ABS_COORD_M:
        bad = int(np.flatnonzero(np.any(np.abs(xyz) > _inputs.MAX_ABS_COORD_M, axis=1))[0])
        raise InputError(
            f"{name}: coordinate beyond +-{_inputs.MAX_ABS_COORD_M:g} m (row {bad}); not a map in "
            "metres"
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
    pose_provenance : which poses placed the detections (:class:`PoseProvenance`; None: unknown).
    """

    frames: np.ndarray
    rover_xyz: np.ndarray
    detections_xyz: np.ndarray
    detection_frame: np.ndarray
    name: str = "traverse"
    pose_provenance: PoseProvenance | None = None

    @property
    def path_length(self) -> float:
        """Length of the rover path in metres."""
        if len(self.rover_xyz) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.rover_xyz, axis=0), axis=1).sum())


# --------------------------------------------------------------------------- traverse CSV


def is_traverse_csv(path: str | Path) -> bool:
    """True if the file's header is the LunarLoc traverse header."""
    return _first_line(path).split(",")[:6] == list(TRAVERSE_COLUMNS)


def _first_line(path: str | Path) -> str:
    """The first line of a text file, lower case without spaces (checked: exists, is a file,
    UTF-8)."""
    with _inputs.open_text(path) as fh:
        try:
            line = fh.readline(_inputs.MAX_CSV_FIELD_CHARS)
        except UnicodeDecodeError as exc:
            raise _inputs.decode_error(path, exc, 1) from None
    return line.strip().lower().replace(" ", "")


def load_traverse(path: str | Path) -> Traverse:
    """Read a LunarLoc traverse CSV (``frame,x,y,z,detections,boulders``).

    Raises FileFormatError naming the file and line for a wrong header, a bad number,
    a malformed boulder list, or a detection count that disagrees with the list.
    """
    path = Path(path)
    with _inputs.open_text(path, what="traverse CSV") as fh, _inputs.csv_field_limit():
        # strict: a quote left open at the end of the file is an error
        reader = csv.reader(fh, strict=True)
        try:
            trav = _read_traverse_rows(path, reader)
        except UnicodeDecodeError as exc:
            raise _inputs.decode_error(path, exc, reader.line_num + 1) from None
        except csv.Error as exc:
            raise _inputs.csv_error(path, reader.line_num, exc) from None
    if trav.pose_provenance is None:
        trav.pose_provenance = _sidecar_provenance(path) or DATASET_PROVENANCE
    return trav


#: a traverse CSV that states no provenance: the LunarLoc dataset's schema places its detections
#: with the ground-truth pose (its README: "already in the WORLD frame (ground-truth pose applied)")
DATASET_PROVENANCE = PoseProvenance(
    POSE_GROUND_TRUTH,
    "",
    "the dataset's traverse schema; the file states none",
)
#: the detect command's configuration beside its traverse CSV (``OUTPUT.config.json``), whose
#: ``info.pose`` named the poses before the ``pose`` column was written
_SIDECAR_SUFFIX = ".config.json"
_MAX_SIDECAR_BYTES = 16 * 1024**2


def _sidecar_provenance(path: Path) -> PoseProvenance | None:
    """The provenance in ``PATH.config.json`` (what ``lunarloc detect`` wrote beside a traverse CSV
    before it wrote the ``pose`` column): ``info.pose`` ``ground-truth...`` or an odometry source's
    name. None where there is no such file; an unreadable one, or one without ``info.pose``, says
    odometry of an unknown source (the safe reading: the localizer keeps its prior)."""
    import json

    side = path.with_name(path.name + _SIDECAR_SUFFIX)
    if not side.is_file():
        return None
    stated_by = f"{side.name} beside the file"
    try:
        _inputs.check_input_file(side, _MAX_SIDECAR_BYTES, "configuration JSON")
        label = json.loads(side.read_text(encoding="utf-8"))["info"]["pose"]
        if not isinstance(label, str):
            raise TypeError("info.pose is not a string")
    except (OSError, ValueError, KeyError, TypeError, LimitError, FileFormatError) as exc:
        log.warning("%s: no pose provenance read (%s); taken as odometry", side, exc)
        return PoseProvenance(POSE_ODOMETRY, "unknown", stated_by + ", unreadable")
    return PoseProvenance.from_label(label, stated_by)


def _read_traverse_rows(path: Path, reader) -> Traverse:
    import array

    # typed arrays, 8 bytes per value: memory follows the file's content, not its row count
    frames, rover, dets, det_frame = (
        array.array("q"),
        array.array("d"),
        array.array("d"),
        array.array("q"),
    )
    try:
        header = next(reader)
    except StopIteration:
        raise FileFormatError(f"{path}: empty file") from None
    header = [h.strip().lower() for h in header]
    if header[:6] != list(TRAVERSE_COLUMNS):
        raise FileFormatError(
            f"{path}:1: expected traverse columns {','.join(TRAVERSE_COLUMNS)}, got "
            f"{','.join(header)}"
        )
    if header[6:] not in ([], [POSE_COLUMN]):
        raise FileFormatError(
            f"{path}:1: unexpected column(s) after boulders: {','.join(header[6:])} "
            f"(a traverse CSV may add '{POSE_COLUMN}' only)"
        )
    width = len(header)
    poses: dict[str, PoseProvenance] = {}  # each distinct pose text, parsed once
    for row in reader:
        line = reader.line_num
        if not row or (len(row) == 1 and not row[0].strip()):
            continue
        if len(row) != width:
            raise FileFormatError(f"{path}:{line}: expected {width} fields, got {len(row)}")
        if width == 7 and row[6] not in poses:
            try:
                poses[row[6]] = PoseProvenance.parse(row[6], f"the file's {POSE_COLUMN} column")
            except InputError as exc:
                raise FileFormatError(f"{path}:{line}: {exc}") from None
        if len(frames) >= _inputs.MAX_CSV_ROWS:
            raise LimitError(f"{path}:{line}: more than {_inputs.MAX_CSV_ROWS:,} data rows")
        try:
            frame = _int_field(row[0], "frame")
            xyz = [_float_field(v) for v in row[1:4]]
            count = _int_field(row[4], "detections")
        except ValueError as exc:
            raise FileFormatError(f"{path}:{line}: {exc}") from None
        text = row[5].strip()
        if not (text.startswith("[") and text.endswith("]")):
            raise FileFormatError(f"{path}:{line}: boulders must be a list like [(x, y, z), ...]")
        try:
            values = parse_boulders(text)
        except ValueError as exc:
            raise FileFormatError(f"{path}:{line}: {exc}") from None
        if len(values) != count:
            raise FileFormatError(
                f"{path}:{line}: detections says {count} but the boulder list has {len(values)} "
                "points"
            )
        if not np.all(np.isfinite(xyz)) or not np.all(np.isfinite(values)):
            raise FileFormatError(f"{path}:{line}: non-finite value")
        if max(map(abs, xyz)) > _inputs.MAX_ABS_COORD_M or (
            values.size and np.max(np.abs(values)) > _inputs.MAX_ABS_COORD_M
        ):
            raise FileFormatError(
                f"{path}:{line}: coordinate beyond +-{_inputs.MAX_ABS_COORD_M:g} m"
            )
        frames.append(frame)
        rover.extend(xyz)
        if count:
            dets.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
            det_frame.frombytes(np.full(count, frame, dtype=np.int64).tobytes())
    if not frames:
        raise FileFormatError(f"{path}: no data rows")
    return Traverse(
        # views of the typed arrays (writable, no copy)
        frames=np.frombuffer(frames, dtype=np.int64),
        rover_xyz=np.frombuffer(rover, dtype=np.float64).reshape(-1, 3),
        detections_xyz=np.frombuffer(dets, dtype=np.float64).reshape(-1, 3),
        detection_frame=np.frombuffer(det_frame, dtype=np.int64),
        name=path.stem,
        pose_provenance=_rows_provenance(poses.values()),
    )


def _rows_provenance(found) -> PoseProvenance | None:
    """The provenance of a traverse from its rows': ground truth only if every row says so
    (any odometry row: odometry, the first such); None when the file has no pose column."""
    found = list(found)
    if not found:
        return None
    odo = [p for p in found if not p.rigid]
    return odo[0] if odo else found[0]


_PLAIN_FLOAT = re.compile(rf"\s*(?:{_NUM}|[-+]?(?:nan|inf|infinity))\s*", re.IGNORECASE)


def _float_field(text: str) -> float:
    """A plain decimal number (``float()`` would also take ``1_000``); nan/inf are read (and
    refused by the caller as non-finite)."""
    if not _PLAIN_FLOAT.fullmatch(text):
        raise ValueError(f"not a number: {text[:40]!r}")
    return float(text)


def _int_field(text: str, name: str) -> int:
    """A plain decimal integer (``int()`` would also take ``1_000`` and spaces inside)."""
    t = text.strip()
    if not re.fullmatch(r"[-+]?\d{1,18}", t):
        raise ValueError(f"{name} must be an integer, got {text[:40]!r}")
    return int(t)


# --------------------------------------------------------------------------- aggregation


@dataclass(frozen=True)
class AggregationConfig:
    """How per-frame detections become landmarks (one per rock).

    DBSCAN (Ester et al. 1996) groups detections of the same rock; the landmark is
    the component-wise median of its group (robust to stray detections).
    Defaults were chosen by measurement on the 17 real LunarLoc traverses
    (docs/results.md, "Landmark clustering").
    """

    radius_m: float = 0.10  # DBSCAN eps: neighbours within this distance belong to one rock
    min_sightings: int = (
        5  # DBSCAN min_samples: detections needed to make a landmark (drops one-off noise)
    )
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
    detection_arc_m: np.ndarray | None = None,
) -> LandmarkMap:
    """Cluster detections (D, 3) into a LandmarkMap (median centre, sighting count).

    `detection_frame` (D,) gives the frame of each detection; with it, `sightings`
    counts distinct frames and `config.min_frames` applies. `detection_arc_m` (D,) gives the
    distance the vehicle had travelled along its path when it took each detection
    (:func:`detection_arcs_m`); with it, the map carries each landmark's sighting arc length
    (mean, least, greatest over its detections).
    """
    from sklearn.cluster import DBSCAN

    cfg = config or AggregationConfig()
    pts = as_points(detections_xyz, "detections")
    arc = None
    if detection_arc_m is not None:
        arc = np.asarray(detection_arc_m, dtype=float).reshape(-1)
        if arc.shape[0] != len(pts) or not np.all(np.isfinite(arc)) or np.any(arc < 0):
            raise InputError(
                f"detection_arc_m must hold {len(pts)} finite non-negative values, got "
                f"{arc.shape[0]}"
            )
    no_arcs = {} if arc is None else {name: np.zeros(0) for name in _ARC_FIELDS}
    if len(pts) == 0:
        return LandmarkMap(np.zeros((0, 3)), sightings=np.zeros(0), frame=frame, **no_arcs)
    labels = DBSCAN(eps=cfg.radius_m, min_samples=cfg.min_sightings).fit_predict(pts)
    keep = labels >= 0
    if not np.any(keep):
        return LandmarkMap(np.zeros((0, 3)), sightings=np.zeros(0), frame=frame, **no_arcs)
    lab = labels[keep]
    order = np.argsort(lab, kind="stable")
    lab_sorted = lab[order]
    pts_sorted = pts[keep][order]
    starts = np.flatnonzero(np.r_[True, lab_sorted[1:] != lab_sorted[:-1]])
    groups = np.split(np.arange(len(lab_sorted)), starts[1:])
    frames_sorted = None if detection_frame is None else np.asarray(detection_frame)[keep][order]
    arc_sorted = None if arc is None else arc[keep][order]
    centres, counts, spreads, arcs = [], [], [], []
    for g in groups:
        n = len(np.unique(frames_sorted[g])) if frames_sorted is not None else len(g)
        if n < cfg.min_frames and frames_sorted is not None:
            continue
        centres.append(np.median(pts_sorted[g], axis=0))
        counts.append(n)
        spreads.append(sighting_sigma(pts_sorted[g], n))
        if arc_sorted is not None:
            a = arc_sorted[g]
            arcs.append((float(np.mean(a)), float(a.min()), float(a.max())))
    if not centres:
        return LandmarkMap(np.zeros((0, 3)), sightings=np.zeros(0), frame=frame, **no_arcs)
    sig = np.asarray(spreads, dtype=float).reshape(-1, 2)
    A = np.asarray(arcs, dtype=float).reshape(-1, 3)
    return LandmarkMap(
        np.asarray(centres),
        sightings=np.asarray(counts, dtype=float),
        frame=frame,
        sigma_xy_m=sig[:, 0],
        sigma_z_m=sig[:, 1],
        **({} if arc is None else dict(zip(_ARC_FIELDS, A.T))),
    )


def sighting_sigma(points_xyz: np.ndarray, n_independent: int) -> tuple[float, float]:
    """1-sigma (horizontal per axis, vertical) uncertainty of a landmark's median from the
    spread of its sightings: the robust spread (1.4826 x median absolute deviation) over
    sqrt(n_independent) (distinct frames: sightings within a frame share its pose error),
    times 1.25 for the median's efficiency."""
    P = np.asarray(points_xyz, dtype=float)
    mad = 1.4826 * np.median(np.abs(P - np.median(P, axis=0)), axis=0)
    k = 1.25 / np.sqrt(max(int(n_independent), 1))
    return float(k * np.sqrt(0.5 * (mad[0] ** 2 + mad[1] ** 2))), float(k * mad[2])


def path_arc_length_m(path_xyz: np.ndarray) -> np.ndarray:
    """(F,) horizontal distance travelled along a path (F, 3) from its first pose: the arc
    length in which :class:`LandmarkMap` states where a landmark was seen from."""
    P = np.asarray(path_xyz, dtype=float).reshape(-1, 3)
    return (
        np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1))]
        if len(P)
        else np.zeros(0)
    )


def detection_arcs_m(
    path_xyz: np.ndarray, path_frame: np.ndarray, detection_frame: np.ndarray
) -> np.ndarray:
    """(D,) arc length along `path_xyz` (F, 3; its poses numbered by `path_frame` (F,)) at which
    each detection was taken (its frame `detection_frame` (D,)). InputError if a detection's
    frame is not a pose of the path."""
    frames = np.asarray(path_frame).reshape(-1)
    arc = path_arc_length_m(path_xyz)
    if len(frames) != len(arc):
        raise InputError(f"path has {len(arc)} poses but {len(frames)} frame numbers")
    det = np.asarray(detection_frame).reshape(-1)
    order = np.argsort(frames, kind="stable")
    pos = np.searchsorted(frames[order], det)
    pos = np.minimum(pos, max(len(frames) - 1, 0))
    if len(det) and (not len(frames) or np.any(frames[order][pos] != det)):
        raise InputError("a detection's frame is not a pose of the path: no arc length for it")
    return arc[order][pos]


def traverse_map(traverse: Traverse, config: AggregationConfig | None = None) -> LandmarkMap:
    """Landmark map of a traverse's detections (frame name = traverse name), with where along
    the traverse's path each landmark was seen from (arc length from its first frame)."""
    arcs = detection_arcs_m(traverse.rover_xyz, traverse.frames, traverse.detection_frame)
    lm = aggregate_detections(
        traverse.detections_xyz,
        traverse.detection_frame,
        config,
        frame=traverse.name,
        detection_arc_m=arcs,
    )
    lm.pose_provenance = traverse.pose_provenance
    return lm


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
        for name in (*_SIGMA_COLUMNS.values(), *_ARC_COLUMNS.values()):
            if getattr(landmarks, name) is not None:
                extra[name] = getattr(landmarks, name)
        if landmarks.pose_provenance is not None:
            extra["pose_provenance"] = np.array(landmarks.pose_provenance.to_text())
        from lunarloc.io.outputs import atomic_path

        with atomic_path(path) as tmp:
            np.savez(
                tmp, positions_xyz=landmarks.positions_xyz, frame=np.array(landmarks.frame), **extra
            )
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
    for col, name in (*_SIGMA_COLUMNS.items(), *_ARC_COLUMNS.items()):
        if getattr(landmarks, name) is not None:
            cols.append(col)
            data.append(getattr(landmarks, name)[:, None])
    table = np.hstack(data) if data else np.zeros((0, 3))
    from lunarloc.io.outputs import atomic_open

    with atomic_open(path, "w", newline="") as fh:
        fh.write(f"# frame: {landmarks.frame}\n")
        if landmarks.pose_provenance is not None:
            fh.write(f"# pose: {landmarks.pose_provenance.to_text()}\n")
        fh.write(",".join(cols) + "\n")
        for row in table:
            fh.write(",".join(f"{v:.6f}" for v in row) + "\n")
    return path


# optional per-landmark uncertainty: CSV column -> LandmarkMap attribute (and .npz array)
_SIGMA_COLUMNS = {"sigma_xy": "sigma_xy_m", "sigma_z": "sigma_z_m"}
# optional sighting arc lengths: CSV column -> LandmarkMap attribute (and .npz array)
_ARC_COLUMNS = dict(zip(("sighting_arc", "sighting_arc_min", "sighting_arc_max"), _ARC_FIELDS))


def read_numeric_csv(
    path: str | Path, required: tuple[str, ...], what: str = "CSV"
) -> tuple[str | None, list[str], np.ndarray]:
    """Stream a numeric CSV (``#`` comment lines first, a header, rows of plain numbers) into
    an (N, columns) float64 array: (frame name from ``# frame: NAME`` or None, header, table).

    Memory is the table itself (8 bytes per value) plus one line; file size, line length and
    row count are bounded (:mod:`lunarloc.io.inputs`). FileFormatError names the file and line
    of a missing column, a bad or non-finite number, or an absurd coordinate."""
    import array

    path = Path(path)
    frame, header, values, k = None, None, array.array("d"), 0
    with _inputs.open_text(path, what=what) as fh:
        try:
            for k, line in enumerate(fh, start=1):
                if len(line) > _inputs.MAX_CSV_FIELD_CHARS:
                    raise LimitError(
                        f"{path}:{k}: line longer than {_inputs.MAX_CSV_FIELD_CHARS:,} characters"
                    )
                if line.startswith("#"):
                    m = re.match(r"#\s*frame:\s*(.+)", line)
                    if m and header is None:
                        frame = m.group(1).strip()
                    continue
                if not line.strip():
                    continue
                parts = line.rstrip("\r\n").split(",")
                if header is None:
                    header = [h.strip().lower() for h in parts]
                    for col in required:
                        if col not in header:
                            raise FileFormatError(
                                f"{path}:{k}: missing column '{col}' (need {','.join(required)}; "
                                f"got {','.join(header)})"
                            )
                    continue
                if len(parts) != len(header):
                    raise FileFormatError(
                        f"{path}:{k}: expected {len(header)} fields, got {len(parts)}"
                    )
                if len(values) >= _inputs.MAX_CSV_ROWS * len(header):
                    raise LimitError(f"{path}:{k}: more than {_inputs.MAX_CSV_ROWS:,} rows")
                try:
                    vals = [_float_field(p) for p in parts]
                except ValueError as exc:
                    raise FileFormatError(f"{path}:{k}: {exc}") from None
                if not all(math.isfinite(v) for v in vals):
                    raise FileFormatError(f"{path}:{k}: non-finite value")
                if max(map(abs, vals)) > _inputs.MAX_ABS_COORD_M:
                    raise FileFormatError(f"{path}:{k}: value beyond +-{_inputs.MAX_ABS_COORD_M:g}")
                values.extend(vals)
        except UnicodeDecodeError as exc:
            raise _inputs.decode_error(path, exc, k + 1) from None
    if header is None:
        raise FileFormatError(f"{path}: no header line")
    return frame, header, np.frombuffer(values, dtype=np.float64).reshape(-1, len(header)).copy()


def _map_csv_provenance(path: Path) -> PoseProvenance | None:
    """The ``# pose: PROVENANCE`` line among a map CSV's leading comment lines (None: none)."""
    with _inputs.open_text(path, what="landmark map CSV") as fh:
        for k, line in enumerate(fh, start=1):
            if not line.startswith("#") or k > 64:
                return None
            m = re.match(r"#\s*pose:\s*(.*)", line[:200])
            if m:
                try:
                    return PoseProvenance.parse(m.group(1), "the file's pose line")
                except InputError as exc:
                    raise FileFormatError(f"{path}:{k}: {exc}") from None
    return None


def _load_map_csv(path: Path) -> LandmarkMap:
    frame, header, table = read_numeric_csv(path, ("x", "y", "z"), "landmark map CSV")
    idx = {name: header.index(name) for name in header}
    provenance = _map_csv_provenance(path)
    try:
        return LandmarkMap(
            table[:, [idx["x"], idx["y"], idx["z"]]],
            table[:, idx["size"]] if "size" in idx else None,
            table[:, idx["sightings"]] if "sightings" in idx else None,
            frame=frame or path.stem,
            **{
                name: table[:, idx[col]]
                for col, name in (*_SIGMA_COLUMNS.items(), *_ARC_COLUMNS.items())
                if col in idx
            },
            pose_provenance=provenance,
        )
    except InputError as exc:
        raise FileFormatError(f"{path}: {exc}") from None


def load_map(path: str | Path, config: AggregationConfig | None = None) -> LandmarkMap:
    """Load a landmark map from ``.csv``/``.npz``; a traverse CSV is aggregated into one.

    Raises FileFormatError naming the file (and line) when it cannot be read.
    """
    path = Path(path)
    if path.suffix.lower() == ".npz":
        return _load_map_npz(path)
    if is_traverse_csv(path):
        return traverse_map(load_traverse(path), config)
    return _load_map_csv(path)


@dataclass(frozen=True)
class VehicleInput:
    """What :func:`lunarloc.localize` needs from a vehicle file (:func:`load_vehicle`).

    ``map``: the vehicle landmark map. From a traverse CSV also ``path_xyz`` (F, 3), the
    rover path that built the map (vehicle frame, m: the localizer measures how far the
    rover drove between landmarks, which bounds or fits the odometry's bend along it), and
    ``query_xyz`` (1, 3), the rover's last position (where the pose will be used, so where
    its error is judged). Both None for a landmark map, whose path is not known.
    Pass them on: ``localize(ref, v.map, query_xyz=v.query_xyz, path_xyz=v.path_xyz)``.
    The map carries the file's pose provenance (:attr:`pose_provenance`): a dataset traverse
    CSV is posed by ground truth, so localize judges it rigid unless bounds are stated.
    """

    map: LandmarkMap
    path_xyz: np.ndarray | None = None
    query_xyz: np.ndarray | None = None
    source: str = "map"

    @property
    def pose_provenance(self) -> PoseProvenance | None:
        """Which poses placed the map's detections, as the file says (None: it does not)."""
        return self.map.pose_provenance

    def localize_kwargs(self) -> dict:
        """``{"query_xyz": ..., "path_xyz": ...}`` for :func:`lunarloc.localize`."""
        return {"query_xyz": self.query_xyz, "path_xyz": self.path_xyz}


def load_vehicle(path: str | Path, config: AggregationConfig | None = None) -> VehicleInput:
    """A vehicle file as :func:`lunarloc.localize` needs it (what ``lunarloc localize`` does
    with its VEHICLE argument, so the API and the CLI give the same answer).

    A LunarLoc traverse CSV gives its landmark map (detections clustered with `config`)
    *and* its path and last position; a landmark map (``.csv``/``.npz``) gives the map
    alone. Raises FileFormatError naming the file (and line) when it cannot be read."""
    path = Path(path)
    if path.suffix.lower() != ".npz" and is_traverse_csv(path):
        trav = load_traverse(path)
        path_xyz = np.asarray(trav.rover_xyz, dtype=float)
        return VehicleInput(
            traverse_map(trav, config),
            path_xyz,
            path_xyz[-1:].copy() if len(path_xyz) else None,
            "traverse",
        )
    return VehicleInput(load_map(path, config))


__all__ += ["VehicleInput", "load_vehicle"]


def format_boulders(points: np.ndarray) -> str:
    """Python-literal list of (x, y, z) tuples, as in the LunarLoc dataset CSVs."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    return "[" + ", ".join(f"({x!r}, {y!r}, {z!r})" for x, y, z in pts.tolist()) + "]"


def save_traverse(path: str | Path, rows, pose_provenance: PoseProvenance) -> int:
    """Write a traverse CSV in the LunarLoc dataset's schema plus the ``pose`` column: rows of
    ``(frame, rover_xyz (3,), detections_xyz (N, 3))``, map frame, m. Every row states
    `pose_provenance` (so a copy of any part of the file still says which poses placed it);
    readers by column name (pandas, :func:`load_traverse`) read the six dataset columns as
    before. Returns the number of rows; InputError for a non-finite pose (nothing is left
    behind: the file is written atomically)."""
    from lunarloc.io.outputs import atomic_open

    if not isinstance(pose_provenance, PoseProvenance):
        raise InputError("save_traverse needs the pose provenance (a PoseProvenance)")
    pose = pose_provenance.to_text()
    n = 0
    with atomic_open(Path(path), "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*TRAVERSE_COLUMNS, POSE_COLUMN])
        for frame, rover_xyz, det_xyz in rows:
            xyz = np.asarray(rover_xyz, dtype=float).reshape(3)
            pts = np.asarray(det_xyz, dtype=float).reshape(-1, 3)
            if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(pts))):
                raise InputError(f"frame {frame}: the rover pose or a detection is not finite")
            x, y, z = (float(v) for v in xyz)
            w.writerow(
                [int(frame), repr(x), repr(y), repr(z), len(pts), format_boulders(pts), pose]
            )
            n += 1
    return n


def _load_map_npz(path: Path) -> LandmarkMap:
    """A `.npz` landmark map, every array checked before it is allocated
    (:func:`lunarloc.io.inputs.load_npz_arrays`)."""
    z = _inputs.load_npz_arrays(path)
    if "positions_xyz" not in z:
        raise FileFormatError(
            f"{path}: not a lunarloc .npz map (no 'positions_xyz' array; has "
            f"{', '.join(z) or 'none'})"
        )
    for name, arr in z.items():
        if name not in ("frame", "pose_provenance") and arr.dtype.kind not in "fiub":
            raise FileFormatError(
                f"{path}: array '{name}' holds {arr.dtype} values, expected numbers"
            )
    frame = z.get("frame")
    if frame is not None and (frame.ndim != 0 or frame.dtype.kind != "U"):
        raise FileFormatError(
            f"{path}: 'frame' must be a single string, got {frame.dtype} of shape {frame.shape}"
        )
    pose = z.get("pose_provenance")
    provenance = None
    if pose is not None:
        if pose.ndim != 0 or pose.dtype.kind != "U":
            raise FileFormatError(f"{path}: 'pose_provenance' must be a single string")
        try:
            provenance = PoseProvenance.parse(str(pose), "the file's pose_provenance array")
        except InputError as exc:
            raise FileFormatError(f"{path}: {exc}") from None
    try:
        return LandmarkMap(
            z["positions_xyz"],
            z.get("sizes"),
            z.get("sightings"),
            str(frame) if frame is not None else path.stem,
            **{
                name: z[name]
                for name in (*_SIGMA_COLUMNS.values(), *_ARC_COLUMNS.values())
                if name in z
            },
            pose_provenance=provenance,
        )
    except InputError as exc:
        raise FileFormatError(f"{path}: {exc}") from None
