"""Read and write `.lac` archives, the Lunar Autonomy Challenge (LAC) recording format.

Layout
------
A `.lac` file is a gzip-compressed tar whose members sit at the archive root
(no top-level folder)::

    initial.toml                      fiducials, lander, rover, [cameras.<Name>]
    metadata.toml                     data_spec, description, start_time, end_time, frames
    frames.csv                        frame,x,y,z,roll,pitch,yaw,accel_x..gyro_z,
                                      mission_time,power,linear_speed,angular_speed,cover_angle
    cameras/<Name>/<Name>_frames.csv  frame,enable,camera_x..camera_yaw,light_intensity,
                                      grayscale,semantic
    cameras/<Name>/grayscale/<Name>_grayscale_<frame>.png
    cameras/<Name>/semantic/<Name>_semantic_<frame>.png
    custom/<record>.csv               extra records (ours: ``rocks``, ``odometry``)

Units: positions in metres, angles in radians (Euler roll/pitch/yaw with
``R = Rz(yaw) Ry(pitch) Rx(roll)``, see :mod:`lunarloc.core.geometry`), accelerations
in m/s^2, angular rates in rad/s, ``mission_time`` in seconds, ``power`` in Wh,
``linear_speed`` in m/s, ``angular_speed`` in rad/s, ``cover_angle`` in radians.
Rover poses are in the map (world) frame; camera poses (``camera_*``) are
relative to the rover (as the LAC's ``get_camera_position`` returns them), and so is
initial.toml's ``lander`` (as ``get_initial_lander_position`` returns it; in real LAC
archives the initial rover pose composed with it puts the lander at the site centre).
:func:`lander_pose_map` gives the map-frame lander pose. Archives lunarloc wrote before
``data_spec = "lunarloc-2"`` (:data:`DATA_SPEC`) stored a map-frame ``lander``; they carry
``data_spec = "lunarloc-sim"`` and the reader converts their ``lander`` on opening.

Compatibility with the published LAC code (verified against the recorder and
reader of ``Robaire/lac-data`` and its copy in ``mit-acl/lunarloc-data``)
-----------------------------------------------------------------------------
* Members are written at the root of the tar, named exactly ``initial.toml``,
  ``metadata.toml``, ``frames.csv``, ``cameras/<Name>/<Name>_frames.csv``,
  ``custom/<name>.csv``; the published reader looks them up by these exact
  names, so a leading ``./`` or a top-level folder would break it. Their README
  draws the camera folders as ``images/<camera>/``, but their recorder and
  reader both use ``cameras/<camera>/``; we follow the code.
* ``grayscale`` / ``semantic`` columns hold the bare image *file name*
  (``FrontLeft_grayscale_20.png``), resolved against
  ``cameras/<Name>/<kind>/``; ``semantic`` is empty when the camera does not
  record semantics. Images may be PNG or JPEG (their recorder has a ``jpg``
  option); they are decoded by content. A semantic image is returned as stored:
  (H, W) or (H, W, 3) (CARLA-style RGB) uint8; 16-bit single-channel PNGs
  (uint16, for more than 255 instance ids) also round-trip.
* ``enable`` is written as ``True``/``False`` (pandas' bool spelling).
* The recorder writes a camera row only for frames where the camera was
  enabled *and* produced an image, and writes a camera CSV only for cameras
  with at least one row. Earlier generations (the MAPLE recorder, April 2025)
  wrote a 1-byte table (``"\n"``, an empty DataFrame) for a camera without
  images, and the first of them put tables and images under ``images/<Name>/``,
  stored the member path (``images/<Name>/grayscale/...png``) in the
  ``grayscale`` column, wrote a row for every frame (empty file name when no
  image) and extra ``light_*`` columns: all read here (empty table = no images). The published
  reader's ``input_data`` therefore fails
  on a row without a grayscale file name (or, for a ``use_semantic`` camera,
  without a semantic one); :class:`LacWriter` refuses to write such rows for
  an enabled camera (it accepts image-less rows only with ``enable=False``,
  which the LAC recorder never writes; avoid them if the archive must replay
  in the published reader).
* The published reader uses pandas and the ``toml`` package (TOML 0.5), which
  rejects arrays mixing ints and floats: the writer stores ``lander`` and
  ``rover`` as floats. Checked offline: archives from :class:`LacWriter` load in
  ``lac_data``'s FrameDataReader / CameraDataReader / PlaybackAgent with
  identical poses and pixels, and archives made by ``lac_data``'s Recorder
  (PNG and JPEG options) load here unchanged.
* ``initial.toml``: ``fiducials`` is a *boolean* (``use_fiducials()``);
  ``lander`` and ``rover`` are ``[x, y, z, roll, pitch, yaw]``; camera tables
  keep whatever types the agent gave (the LAC example agent gives
  ``width``/``height`` as strings, e.g. ``"1280"``). Older recorder generations
  passed numpy scalars to the ``toml`` package, which writes them as strings
  (``"1.5"``, or ``"np.float64(1.5)"`` under numpy 2). :attr:`LacArchive.initial`
  holds numbers (``initial_raw`` the text as stored); a value that is not a
  number raises ArchiveError naming the key.
* ``metadata.toml``: the LAC recorder writes ``data_spec = "0.1"``, times as
  ``"%Y-%m-%d %H:%M:%S"`` wall-clock strings and ``frames`` = number of rows
  of ``frames.csv``. Ours writes the same keys and formats, with our own
  ``data_spec`` string.
* The recorder also adds a ``.gitignore`` member (``*``); we write one too and
  ignore it when reading. Its custom records always begin with a ``frame``
  column; ours need not (e.g. ``rocks``). Record names must not contain a dot
  (their reader cuts the name at the first one).
* Floats are written by :func:`float_text` so that this reader and pandas'
  default C parser (pandas 2.2, what lac-data pins) read the *same* value: the
  shortest repr when pandas reads it exactly (then bit-exact), else rounded to
  15 significant digits (relative change < 5e-15). The plain repr is not enough:
  pandas' parser keeps 17 digits, leading zeros included, and rounds twice.

Reading strategy (random access into a gzip stream)
---------------------------------------------------
gzip is not seekable, and the LAC recorder writes the tables *after* all the
images, so the first open must decompress the whole archive once. During that
single pass we record the tar member index (name -> offset into the
decompressed stream) and, every ``checkpoint_spacing`` decompressed bytes
(4 MiB), a snapshot of the zlib decompressor (``zlib.Decompress.copy()``: about
the 32 KiB window plus state, ~40 KiB each (measured)). Reading a member later restores the
nearest checkpoint at or before it and decompresses at most one spacing forward,
so random access costs O(spacing), not O(archive). Reads that move forward
continue the live decompressor, so sequential iteration is linear in the archive
length. This needs no extra dependency (``indexed_gzip`` would do the same in C)
and no temporary disk copy (decompressing to a temporary tar would cost a full
extra write of the archive, gigabytes for long traverses).

Measured on the 2-core dev machine with a 200 MB archive (300 frames, 450
1280x720 PNGs): open + index 0.15-0.2 s; random access to one image member
~5 ms (plus ~15-20 ms PNG decode), against 56-107 ms for ``tarfile`` r:gz, whose
cost grows with the archive length; sequential ``iter_frames`` 65-83 images/s,
bound by PNG decoding.
"""

from __future__ import annotations

import io
import logging
import os
import re
import tarfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lunarloc.core.errors import ArchiveError, InputError, LimitError

from lunarloc.io.lac.format import (
    CAMERA_COLUMNS,
    DATA_SPEC,
    FRAME_COLUMNS,
    LEGACY_MAP_LANDER_SPECS,
    STATE_COLUMNS,
    lander_pose_map,
    lander_pose_relative,
)
from lunarloc.io.lac.gzindex import DEFAULT_CHECKPOINT_SPACING, _GzipIndexError, _IndexedGzipReader
from lunarloc.io.lac.tables import Table, _parse_csv, _parse_int

# re-exported: one import for reading and writing
from lunarloc.io.lac.writer import LacWriter, float_text

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

__all__ = [
    "FRAME_COLUMNS",
    "CAMERA_COLUMNS",
    "STATE_COLUMNS",
    "Table",
    "FrameRecord",
    "LacArchive",
    "LacWriter",
    "float_text",
    "DATA_SPEC",
    "LEGACY_MAP_LANDER_SPECS",
    "lander_pose_map",
    "lander_pose_relative",
]

_CAMERA_FLOAT_COLUMNS = CAMERA_COLUMNS[2:9]
_CAMERA_STRING_COLUMNS = ("grayscale", "semantic")
_IMAGE_KINDS = ("grayscale", "semantic")
_INITIAL_KEYS = ("fiducials", "lander", "rover", "cameras")
_METADATA_KEYS = ("data_spec", "description", "start_time", "end_time", "frames")
_NUMPY_SCALAR_TEXT = re.compile(r"^\s*(?:np|numpy)\.(?:float|int)\d*\((.*)\)\s*$")
_CAMERA_ROOTS = ("cameras", "images")  # the recorder's layout; the first MAPLE recorder's

# Limits on what an archive may make us allocate, checked before reading (docs/robustness.md).
# one CSV member (frames.csv of a 20 Hz traverse: ~400 B/row, ~180 h)
MAX_TABLE_BYTES = 256 * 1024**2
MAX_TOML_BYTES = 1024**2  # initial.toml / metadata.toml
MAX_IMAGE_BYTES = 64 * 1024**2  # one encoded image member
MAX_IMAGE_PIXELS = (
    64_000_000  # decoded image size (a 2x2 mosaic of 4K frames); PIL's bomb check is 179 M
)
MAX_TAR_HEADER_BYTES = 1024**2  # a GNU long-name or pax extended header
MAX_MEMBERS = 1_000_000  # tar members (a 1 h traverse, 8 cameras at 10 Hz with semantics: ~600 k)


#: ground truth, IMU and time values beyond this are not a rover's (metres, radians, m/s^2, seconds)
MAX_STATE_VALUE = 1e7
#: a camera mounted on the rover: offsets (m) and angles (rad) within this
MAX_CAMERA_OFFSET = 100.0


class _BoundedTarInfo(tarfile.TarInfo):
    """TarInfo that refuses oversized long-name / pax headers (tarfile would read them
    whole into memory) and archives with more than MAX_MEMBERS members."""

    def _proc_member(self, tf):
        if (
            self.type
            in (
                tarfile.GNUTYPE_LONGNAME,
                tarfile.GNUTYPE_LONGLINK,
                tarfile.XHDTYPE,
                tarfile.XGLTYPE,
                tarfile.SOLARIS_XHDTYPE,
            )
            and self.size > MAX_TAR_HEADER_BYTES
        ):
            raise LimitError(
                f"tar header at byte {self.offset} is {self.size:,} bytes, over the "
                f"{MAX_TAR_HEADER_BYTES:,}-byte limit for a long-name/pax header"
            )
        if len(tf.members) >= MAX_MEMBERS:
            raise LimitError(f"more than {MAX_MEMBERS:,} members")
        return super()._proc_member(tf)


# --------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------


@dataclass
class FrameRecord:
    """One frame of an archive, as yielded by :meth:`LacArchive.iter_frames`.

    ``state`` maps the frames.csv columns to values (SI units, see module doc);
    ``cameras`` maps camera name -> its camera-table row at this frame (only cameras
    with a row here); ``grayscale`` / ``semantic`` map camera name -> image
    (only filled when images were requested and present).
    """

    index: int
    frame: int
    state: dict[str, float]
    cameras: dict[str, dict[str, Any]] = field(default_factory=dict)
    grayscale: dict[str, np.ndarray] = field(default_factory=dict)
    semantic: dict[str, np.ndarray] = field(default_factory=dict)


class LacArchive:
    """Reader for a `.lac` archive (gzip tar in the LAC layout). Use as a context manager.

    Opening decompresses the archive once to index its members and loads the small
    tables (TOML, CSV); images are read on demand. Raises ArchiveError (naming the
    archive and the member) for malformed archives, FileNotFoundError if absent.

    Parameters
    ----------
    path : the `.lac` file.
    checkpoint_spacing : decompressed bytes between random-access checkpoints
        (memory ~40 KiB per checkpoint; random access decompresses at most this much).
    """

    def __init__(
        self, path: str | os.PathLike, *, checkpoint_spacing: int = DEFAULT_CHECKPOINT_SPACING
    ):
        from lunarloc.core.errors import file_error
        from lunarloc.io.inputs import check_input_file

        self.path = check_input_file(path, None, ".lac archive")
        t0 = time.perf_counter()
        try:
            self._file = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise file_error(self.path, exc) from None
        try:
            self._open(checkpoint_spacing)
        except BaseException:
            self.close()
            raise
        logger.debug(
            "indexed %s: %d members, %d checkpoints in %.3f s",
            self.path,
            len(self._members),
            self._stream.n_checkpoints,
            time.perf_counter() - t0,
        )

    # -- opening -------------------------------------------------------------------
    def _err(self, member: str | None, msg: str) -> ArchiveError:
        where = f"{self.path}" if member is None else f"{self.path}: {member}"
        return ArchiveError(f"{where}: {msg}")

    def _open(self, spacing: int) -> None:
        magic = self._file.read(2)
        self._file.seek(0)
        if magic != b"\x1f\x8b":
            raise self._err(None, "not a gzip file (a .lac archive is a gzip-compressed tar)")
        self._stream = _IndexedGzipReader(self._file, spacing)
        try:
            self._tar = tarfile.open(fileobj=self._stream, mode="r:", tarinfo=_BoundedTarInfo)
            members = self._tar.getmembers()
            self._stream.read_to_end()  # verify the gzip trailer (CRC, length)
        except _GzipIndexError as exc:
            raise self._err(None, str(exc)) from None
        except tarfile.TarError as exc:
            raise self._err(None, f"not a valid tar archive ({exc})") from None
        except LimitError as exc:
            raise self._err(None, str(exc)) from None
        self._members: dict[str, tarfile.TarInfo] = {}
        for m in members:
            if m.isfile():
                name = m.name[2:] if m.name.startswith("./") else m.name
                self._members[name] = m
        # Tolerate archives re-packed with a single top-level folder.
        self._prefix = ""
        if "initial.toml" not in self._members:
            tops = [n[: -len("initial.toml")] for n in self._members if n.endswith("/initial.toml")]
            if len(tops) == 1 and tops[0].count("/") == 1:
                self._prefix = tops[0]
                self._members = {
                    n[len(self._prefix) :]: m
                    for n, m in self._members.items()
                    if n.startswith(self._prefix)
                }
        self.initial_raw = self._read_toml("initial.toml", _INITIAL_KEYS)
        self.metadata = self._read_toml("metadata.toml", ())
        missing = [k for k in _METADATA_KEYS if k not in self.metadata]
        if missing:
            logger.warning("%s: metadata.toml lacks %s", self.path, ", ".join(missing))
        if not isinstance(self.initial_raw.get("cameras"), dict):
            raise self._err("initial.toml", "'cameras' must be a table")
        self.initial = self._normalized_initial(self.initial_raw)
        self._check_camera_configs()
        self.frames = _parse_csv(
            self._read_member("frames.csv"),
            f"{self.path}: frames.csv",
            required=FRAME_COLUMNS,
            ints=("frame",),
            floats=STATE_COLUMNS,
        )
        self._frame_index = self._index_frames(self.frames["frame"], "frames.csv")
        self._camera_tables: dict[str, Table] = {}
        self._camera_index: dict[str, dict[int, int]] = {}
        self._camera_root: dict[str, str] = {}
        for name in self.initial["cameras"]:
            # `cameras/` (the recorder) or `images/` (the first MAPLE recorder, the READMEs)
            root = next(
                (r for r in _CAMERA_ROOTS if f"{r}/{name}/{name}_frames.csv" in self._members), None
            )
            if root is None:
                continue  # the recorder writes no table for cameras that never produced an image
            member = f"{root}/{name}/{name}_frames.csv"
            table = _parse_csv(
                self._read_member(member),
                f"{self.path}: {member}",
                required=CAMERA_COLUMNS,
                ints=("frame",),
                bools=("enable",),
                floats=_CAMERA_FLOAT_COLUMNS,
                strings=_CAMERA_STRING_COLUMNS,
                allow_empty=True,
            )
            if not table.columns:
                # older recorders wrote a 1-byte table ("\n") for a camera without images
                logger.debug("%s: %s is empty: no images from %s", self.path, member, name)
                continue
            self._camera_root[name] = root
            for kind in _IMAGE_KINDS:  # empty / "nan" (pandas NaN) means no image
                col = table[kind]
                for i, v in enumerate(col):
                    s = v.strip()
                    col[i] = "" if s.lower() == "nan" else s
            self._check_camera_poses(table, member)
            self._camera_tables[name] = table
            self._camera_index[name] = self._index_frames(table["frame"], member)
            self._check_images(name, table, member)

    def _check_camera_poses(self, table: Table, member: str) -> None:
        """The camera's pose (camera_x..camera_yaw) at every row with an image must be finite
        and on the rover (within +-MAX_CAMERA_OFFSET metres / radians): a NaN there was an
        internal error in `run`."""
        used = np.array([bool(v) for v in table["grayscale"]], bool)
        if not used.any():
            return
        cols = ("camera_x", "camera_y", "camera_z", "camera_roll", "camera_pitch", "camera_yaw")
        a = table.to_array(cols)[used]
        bad = ~np.isfinite(a) | (np.abs(np.nan_to_num(a, nan=0.0)) > MAX_CAMERA_OFFSET)
        if np.any(bad):
            i, k = (int(x) for x in np.argwhere(bad)[0])
            line = int(np.flatnonzero(used)[i]) + 2
            raise self._err(
                member,
                f"line {line}, column {cols[k]}: {a[i, k]!r} is not a camera pose on the rover "
                f"(finite, within +-{MAX_CAMERA_OFFSET:g})",
            )

    def _check_camera_configs(self) -> None:
        """Camera tables of initial.toml: width/height positive integers (numbers or numeric
        strings, as LAC agents write them), fov finite in (0, 180) degrees."""
        for name, cfg in self.initial["cameras"].items():
            if not isinstance(cfg, dict):
                raise self._err("initial.toml", f"[cameras.{name}] must be a table")
            for key in ("width", "height"):
                if key in cfg:
                    v = cfg[key]
                    try:
                        n = _parse_int(str(v)) if not isinstance(v, bool) else -1
                    except ValueError:
                        n = -1
                    if not 0 < n <= 100_000:
                        raise self._err(
                            "initial.toml",
                            f"[cameras.{name}] {key} = {str(v)[:40]!r}: expected a positive "
                            "integer (pixels)",
                        )
            for key in ("fov", "hfov_deg"):
                if key in cfg:
                    v = cfg[key]
                    try:
                        f = float(v) if not isinstance(v, bool) else float("nan")
                    except (TypeError, ValueError):
                        f = float("nan")
                    if not 0.0 < f < 180.0:
                        raise self._err(
                            "initial.toml",
                            f"[cameras.{name}] {key} = {str(v)[:40]!r}: expected degrees in (0, "
                            "180)",
                        )

    def _index_frames(self, frames: np.ndarray, member: str) -> dict[int, int]:
        index: dict[int, int] = {}
        for i, f in enumerate(frames.tolist()):
            if f in index:
                raise self._err(
                    member, f"frame {f} appears twice (lines {index[f] + 2} and {i + 2})"
                )
            index[f] = i
        if len(frames) > 1 and np.any(np.diff(frames) < 0):
            raise self._err(member, "frame numbers are not in increasing order")
        return index

    def _check_images(self, camera: str, table: Table, member: str) -> None:
        for kind in _IMAGE_KINDS:
            for i, fname in enumerate(table[kind]):
                if fname and self._image_member(camera, kind, fname) not in self._members:
                    raise self._err(
                        self._image_member(camera, kind, fname),
                        f"image listed in {member} line {i + 2} (frame {int(table['frame'][i])}) "
                        "is absent from the archive",
                    )

    def _image_member(self, camera: str, kind: str, fname: str) -> str:
        """Member of an image named in a camera table: a bare file name (the recorder) is
        resolved in the table's folder; the first recorders stored the member path itself."""
        if "/" in fname:
            return fname
        root = self._camera_root.get(camera, _CAMERA_ROOTS[0])
        member = f"{root}/{camera}/{kind}/{fname}"
        if member not in self._members:  # images in the other layout than the table
            other = next(
                (f"{r}/{camera}/{kind}/{fname}" for r in _CAMERA_ROOTS if r != root), member
            )
            if other in self._members:
                return other
        return member

    # -- initial.toml ----------------------------------------------------------------
    def _number(self, value: Any, key: str, kind: type = float) -> Any:
        """A TOML number, or a number stored as a string (older recorder generations: the
        ``toml`` package writes numpy scalars as strings, e.g. ``"1.5"`` or
        ``"np.float64(1.5)"``)."""
        if isinstance(value, bool):
            raise self._err("initial.toml", f"'{key}' must be a number, got {value!r}")
        if isinstance(value, (int, float)):
            v = float(value)
            if kind is float:
                return v
            if np.isfinite(v) and v == int(v):
                return int(v)  # 640 or 640.0, never a silently truncated 64.5
            raise self._err("initial.toml", f"'{key}' must be a whole number, got {value!r}")
        if isinstance(value, str):
            text = value.strip()
            m = _NUMPY_SCALAR_TEXT.match(text)
            text = m.group(1).strip() if m else text
            try:
                v = float(text)
            except ValueError:
                pass
            else:
                if kind is float:
                    return v
                if np.isfinite(v) and v == int(v):
                    return int(v)
        raise self._err("initial.toml", f"'{key}' must be a number, got {value!r}")

    def _flag(self, value: Any, key: str) -> bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in ("true", "false", "1", "0"):
            return value.strip().lower() in ("true", "1")
        if isinstance(value, (int, float)) and value in (0, 1):
            return bool(value)
        raise self._err("initial.toml", f"'{key}' must be a boolean, got {value!r}")

    def _normalized_initial(self, raw: dict) -> dict:
        """initial.toml with numbers stored as strings parsed, and ``lander`` relative to the
        rover (converted from the map frame for archives lunarloc wrote before DATA_SPEC)."""
        out = dict(raw)
        for key in ("lander", "rover"):
            v = raw[key]
            if not isinstance(v, (list, tuple)) or len(v) != 6:
                raise self._err(
                    "initial.toml", f"'{key}' must be [x, y, z, roll, pitch, yaw], got {v!r}"
                )
            out[key] = [self._number(x, f"{key}[{i}]") for i, x in enumerate(v)]
        if "fiducials" in raw:
            out["fiducials"] = self._flag(raw["fiducials"], "fiducials")
        cams = {}
        for name, cfg in raw["cameras"].items():
            if not isinstance(cfg, dict):
                raise self._err("initial.toml", f"[cameras.{name}] must be a table")
            c = dict(cfg)
            for k, kind in (("width", int), ("height", int), ("light_intensity", float)):
                if k in c:
                    c[k] = self._number(c[k], f"cameras.{name}.{k}", kind)
            for k in ("camera_active", "use_semantic"):
                if k in c:
                    c[k] = self._flag(c[k], f"cameras.{name}.{k}")
            cams[name] = c
        out["cameras"] = cams
        if self.lander_stored_in_map_frame:
            from lunarloc.core.geometry import invert_transform, matrix_to_pose, pose_to_matrix

            T_map_lander = pose_to_matrix(*out["lander"])
            T_map_rover = pose_to_matrix(*out["rover"])
            out["lander"] = [
                float(v) for v in matrix_to_pose(invert_transform(T_map_rover) @ T_map_lander)
            ]
        return out

    @property
    def lander_stored_in_map_frame(self) -> bool:
        """True for archives lunarloc wrote before :data:`DATA_SPEC` (``data_spec`` in
        :data:`LEGACY_MAP_LANDER_SPECS`), whose initial.toml ``lander`` is a map-frame pose.
        ``initial["lander"]`` is rover-relative either way (``initial_raw`` keeps the text)."""
        return str(self.metadata.get("data_spec", "")) in LEGACY_MAP_LANDER_SPECS

    def initial_rover_pose(self) -> np.ndarray:
        """``T_map_rover`` (4x4) at the start: initial.toml ``rover`` (LAC
        ``get_initial_position``)."""
        from lunarloc.core.geometry import pose_to_matrix

        return pose_to_matrix(*self.initial["rover"])

    def lander_pose_map(self) -> list[float]:
        """The lander's pose in the map frame, [x, y, z, roll, pitch, yaw] (m, rad): the initial
        rover pose composed with the rover-relative ``lander`` of initial.toml."""
        return lander_pose_map(self.initial)

    def _read_member(self, name: str) -> bytes:
        info = self._members.get(name)
        if info is None:
            raise self._err(name, "member is missing")
        limit = (
            MAX_TOML_BYTES
            if name.endswith(".toml")
            else MAX_TABLE_BYTES
            if name.endswith(".csv")
            else MAX_IMAGE_BYTES
        )
        if info.size > limit:
            raise self._err(
                name,
                f"member is {info.size:,} bytes, over the {limit:,}-byte limit for this kind of "
                "member",
            )
        try:
            fobj = self._tar.extractfile(info)
            data = fobj.read() if fobj is not None else b""
        except _GzipIndexError as exc:
            raise self._err(name, str(exc)) from None
        if len(data) != info.size:
            raise self._err(name, f"member is truncated ({len(data)} of {info.size} bytes)")
        return data

    def _read_toml(self, name: str, required: Sequence[str]) -> dict:
        data = self._read_member(name)
        try:
            doc = tomllib.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise self._err(name, f"invalid TOML ({exc})") from None
        except RecursionError:
            raise self._err(name, "invalid TOML (nested too deeply)") from None
        missing = [k for k in required if k not in doc]
        if missing:
            raise self._err(name, f"missing key(s) {', '.join(missing)}")
        return doc

    # -- context manager -------------------------------------------------------------
    def close(self) -> None:
        """Release the file handle (idempotent)."""
        f = getattr(self, "_file", None)
        if f is not None:
            f.close()
            self._file = None

    def __enter__(self) -> LacArchive:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"LacArchive({str(self.path)!r}, frames={self.n_frames}, cameras={self.cameras})"

    # -- tables ----------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of rows in frames.csv."""
        return self.frames.n_rows

    @property
    def frame_numbers(self) -> np.ndarray:
        """(N,) int64 frame numbers, increasing."""
        return self.frames["frame"]

    @property
    def cameras(self) -> list[str]:
        """Cameras that have a camera table (recorded at least one frame)."""
        return list(self._camera_tables)

    @property
    def configured_cameras(self) -> dict[str, dict]:
        """The ``[cameras.<Name>]`` tables of initial.toml (all configured cameras)."""
        return self.initial["cameras"]

    def camera_frames(self, camera: str) -> Table:
        """The camera table of `camera` (an empty Table if it recorded nothing)."""
        if camera in self._camera_tables:
            return self._camera_tables[camera]
        if camera in self.initial["cameras"]:
            return Table({c: np.array([]) for c in CAMERA_COLUMNS}, camera)
        raise InputError(
            f"{self.path}: no camera named {camera!r} (have {', '.join(self.initial['cameras'])})"
        )

    def camera_row(self, camera: str, frame: int) -> dict[str, Any] | None:
        """The camera-table row of `camera` at exactly `frame`, or None."""
        idx = self._camera_index.get(camera, {}).get(int(frame))
        return None if idx is None else self._camera_tables[camera].row(idx)

    def image_count(self, camera: str, kind: str = "grayscale") -> int:
        """Number of `kind` images recorded for `camera`."""
        if camera not in self._camera_tables:
            return 0
        return int(sum(1 for v in self._camera_tables[camera][kind] if v))

    @property
    def custom_records(self) -> list[str]:
        """Names of the ``custom/<name>.csv`` records."""
        return sorted(
            n[len("custom/") : -len(".csv")]
            for n in self._members
            if n.startswith("custom/") and n.endswith(".csv") and n.count("/") == 1
        )

    def custom(self, name: str) -> Table:
        """The custom record `name` as a Table (numeric columns float64, others str)."""
        member = f"custom/{name}.csv"
        if member not in self._members:
            raise self._err(
                member,
                f"no custom record {name!r} (have: {', '.join(self.custom_records) or 'none'})",
            )
        return _parse_csv(self._read_member(member), f"{self.path}: {member}")

    def has_member(self, name: str) -> bool:
        return name in self._members

    @property
    def member_names(self) -> list[str]:
        return list(self._members)

    # -- images ----------------------------------------------------------------------
    def image_member(self, camera: str, frame: int, kind: str = "grayscale") -> str | None:
        """Archive member path of an image, or None when that camera has no such image at
        `frame`."""
        if kind not in _IMAGE_KINDS:
            raise InputError(f"image kind must be 'grayscale' or 'semantic', got {kind!r}")
        idx = self._camera_index.get(camera, {}).get(int(frame))
        if idx is None:
            return None
        fname = self._camera_tables[camera][kind][idx]
        return self._image_member(camera, kind, fname) if fname else None

    def read_image(self, member: str) -> np.ndarray:
        """Decode the image stored at archive member `member` (numpy, dtype as stored)."""
        from PIL import Image, UnidentifiedImageError

        data = self._read_member(member)
        try:
            with Image.open(io.BytesIO(data)) as img:
                w, h = img.size  # from the header, before decoding
                if w * h > MAX_IMAGE_PIXELS:
                    raise self._err(
                        member,
                        f"image is {w}x{h} pixels, over the {MAX_IMAGE_PIXELS:,}-pixel limit",
                    )
                return np.array(img)
        except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
            if isinstance(exc, ArchiveError):
                raise
            raise self._err(member, f"cannot decode image ({exc})") from None

    def image(self, camera: str, frame: int, kind: str = "grayscale") -> np.ndarray | None:
        """Image of `camera` at `frame`: grayscale (H, W) uint8, semantic (H, W[, 3]); None if
        absent."""
        member = self.image_member(camera, frame, kind)
        return None if member is None else self.read_image(member)

    def grayscale(self, camera: str, frame: int) -> np.ndarray | None:
        """(H, W) uint8 grayscale image of `camera` at `frame`, or None if none was recorded."""
        return self.image(camera, frame, "grayscale")

    def semantic(self, camera: str, frame: int) -> np.ndarray | None:
        """Semantic image of `camera` at `frame` ((H, W) or (H, W, 3)), or None."""
        return self.image(camera, frame, "semantic")

    def read_images(
        self, requests: Sequence[tuple[str, int, str]]
    ) -> dict[tuple[str, int, str], np.ndarray]:
        """Read several images in archive order (keeps decompression forward-only).

        `requests` holds (camera, frame, kind); absent images are left out of the result.
        """
        found = []
        for req in requests:
            member = self.image_member(*req)
            if member is not None:
                found.append((self._members[member].offset_data, req, member))
        found.sort(key=lambda t: t[0])
        return {req: self.read_image(member) for _, req, member in found}

    # -- iteration -------------------------------------------------------------------
    def frame_state(self, index: int) -> dict[str, float]:
        """frames.csv row number `index` (0-based) as a dict."""
        return self.frames.row(index)

    def iter_frames(self, *, images: bool = True, semantic: bool = True) -> Iterator[FrameRecord]:
        """Yield every frame in order, with camera rows and (optionally) images.

        Images are decompressed forward-only, so a full pass is linear in archive size.
        """
        frames = self.frames["frame"].tolist()
        for i, f in enumerate(frames):
            rec = FrameRecord(index=i, frame=f, state=self.frames.row(i))
            for cam in self._camera_tables:
                row = self.camera_row(cam, f)
                if row is not None:
                    rec.cameras[cam] = row
            if images and rec.cameras:
                kinds = ("grayscale", "semantic") if semantic else ("grayscale",)
                got = self.read_images([(c, f, k) for c in rec.cameras for k in kinds])
                for (cam, _, kind), img in got.items():
                    getattr(rec, kind)[cam] = img
            yield rec

    def __iter__(self) -> Iterator[FrameRecord]:
        return self.iter_frames()

    # -- summaries -------------------------------------------------------------------
    def positions(self) -> np.ndarray:
        """(N, 3) ground-truth rover positions from frames.csv, metres (finite, checked)."""
        return self.finite_columns(("x", "y", "z"), "ground truth")

    def poses(self) -> np.ndarray:
        """(N, 6) rover poses [x, y, z, roll, pitch, yaw] from frames.csv (finite, checked)."""
        return self.finite_columns(("x", "y", "z", "roll", "pitch", "yaw"), "ground truth")

    def finite_columns(
        self, columns: Sequence[str], what: str, limit: float = MAX_STATE_VALUE
    ) -> np.ndarray:
        """frames.csv's `columns` as an (N, k) array; ArchiveError naming the line and column of
        the first value that is not finite or beyond +-`limit` (a NaN in the ground truth made
        ``run`` exit 0 with ``ATE nan``)."""
        a = self.frames.to_array(tuple(columns))
        bad = ~np.isfinite(a) | (
            np.abs(np.nan_to_num(a, nan=0.0, posinf=np.inf, neginf=np.inf)) > limit
        )
        if np.any(bad):
            i, k = (int(x) for x in np.argwhere(bad)[0])
            raise self._err(
                "frames.csv",
                f"line {i + 2}, column {columns[k]}: {a[i, k]!r} is not a usable {what} "
                f"value (finite, within +-{limit:g}; {int(bad.sum())} such cell(s))",
            )
        return a

    def path_length(self) -> float:
        """Length of the ground-truth path, metres (sum of 3D steps between frames)."""
        p = self.positions()
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0

    def duration(self) -> float:
        """Mission time spanned by frames.csv, seconds."""
        t = self.frames["mission_time"]
        return float(np.nanmax(t) - np.nanmin(t)) if len(t) else 0.0
