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
  image) and extra ``light_*`` columns: all read here (empty table = no images). The published reader's ``input_data`` therefore fails
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

import csv
import io
import logging
import math
import os
import re
import tarfile
import tempfile
import time
import zlib
from bisect import bisect_right
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from lunarloc.core.errors import ArchiveError, InputError, LimitError, MissingColumnError

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
    "DATA_SPEC",
    "LEGACY_MAP_LANDER_SPECS",
    "float_text",
    "lander_pose_map",
    "lander_pose_relative",
]

FRAME_COLUMNS: tuple[str, ...] = (
    "frame", "x", "y", "z", "roll", "pitch", "yaw",
    "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z",
    "mission_time", "power", "linear_speed", "angular_speed", "cover_angle",
)  # fmt: skip
"""Columns of ``frames.csv``, in the LAC recorder's order."""

STATE_COLUMNS: tuple[str, ...] = FRAME_COLUMNS[1:]
"""Per-frame state columns (all float) accepted by :meth:`LacWriter.add_frame`."""

CAMERA_COLUMNS: tuple[str, ...] = (
    "frame", "enable", "camera_x", "camera_y", "camera_z",
    "camera_roll", "camera_pitch", "camera_yaw", "light_intensity", "grayscale", "semantic",
)  # fmt: skip
"""Columns of ``cameras/<Name>/<Name>_frames.csv``."""

_CAMERA_FLOAT_COLUMNS = CAMERA_COLUMNS[2:9]
_CAMERA_STRING_COLUMNS = ("grayscale", "semantic")
_IMAGE_KINDS = ("grayscale", "semantic")
_INITIAL_KEYS = ("fiducials", "lander", "rover", "cameras")
_METADATA_KEYS = ("data_spec", "description", "start_time", "end_time", "frames")
_TIME_FORMAT = "%Y-%m-%d %H:%M:%S"
_RECORD_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_CAMERA_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_INT_TEXT = re.compile(r"^\s*[-+]?\d+\s*$")
_NUMPY_SCALAR_TEXT = re.compile(r"^\s*(?:np|numpy)\.(?:float|int)\d*\((.*)\)\s*$")
_CAMERA_ROOTS = ("cameras", "images")  # the recorder's layout; the first MAPLE recorder's

DATA_SPEC = "lunarloc-2"
"""``data_spec`` :class:`LacWriter` writes: ``lander`` in initial.toml is relative to the
rover (as the LAC recorder stores it)."""

LEGACY_MAP_LANDER_SPECS: tuple[str, ...] = ("lunarloc-sim",)
"""``data_spec`` values of archives lunarloc wrote before :data:`DATA_SPEC`, whose
``lander`` is a map-frame pose; the reader converts it to rover-relative."""

_CHUNK = 256 * 1024  # compressed bytes read per step
_MAX_OUT = 1024 * 1024  # cap on decompressed bytes per zlib call (bounds memory)
DEFAULT_CHECKPOINT_SPACING = 4 * 1024 * 1024  # decompressed bytes between checkpoints

# Limits on what an archive may make us allocate, checked before reading (docs/robustness.md).
MAX_TABLE_BYTES = 256 * 1024**2  # one CSV member (frames.csv of a 20 Hz traverse: ~400 B/row, ~180 h)
MAX_TABLE_CELLS = 5_000_000  # rows x columns of one CSV member (frames.csv: 18 columns, 277 k rows = 3.9 h at 20 Hz)
MAX_TOML_BYTES = 1024**2  # initial.toml / metadata.toml
MAX_IMAGE_BYTES = 64 * 1024**2  # one encoded image member
MAX_IMAGE_PIXELS = 64_000_000  # decoded image size (a 2x2 mosaic of 4K frames); PIL's bomb check is 179 M
MAX_TAR_HEADER_BYTES = 1024**2  # a GNU long-name or pax extended header
MAX_MEMBERS = 1_000_000  # tar members (a 1 h traverse, 8 cameras at 10 Hz with semantics: ~600 k)
MAX_CSV_FIELD = 1024**2  # characters in one CSV field of an archive table


class _BoundedTarInfo(tarfile.TarInfo):
    """TarInfo that refuses oversized long-name / pax headers (tarfile would read them
    whole into memory) and archives with more than MAX_MEMBERS members."""

    def _proc_member(self, tf):
        if self.type in (tarfile.GNUTYPE_LONGNAME, tarfile.GNUTYPE_LONGLINK, tarfile.XHDTYPE, tarfile.XGLTYPE,
                         tarfile.SOLARIS_XHDTYPE) and self.size > MAX_TAR_HEADER_BYTES:  # fmt: skip
            raise LimitError(f"tar header at byte {self.offset} is {self.size:,} bytes, over the "
                             f"{MAX_TAR_HEADER_BYTES:,}-byte limit for a long-name/pax header")  # fmt: skip
        if len(tf.members) >= MAX_MEMBERS:
            raise LimitError(f"more than {MAX_MEMBERS:,} members")
        return super()._proc_member(tf)


# --------------------------------------------------------------------------------------
# Seekable view of a gzip file (single pass index + decompressor checkpoints)
# --------------------------------------------------------------------------------------


class _GzipIndexError(Exception):
    """Internal: corrupt or truncated gzip data (wrapped into ArchiveError by the caller)."""


class _IndexedGzipReader(io.RawIOBase):
    """Read-only, seekable file over the decompressed content of a gzip file.

    Seeking backwards restores the nearest decompressor checkpoint at or before the
    target; seeking forwards continues decompression (or jumps to a closer
    checkpoint). Checkpoints are taken while decompressing new territory.
    """

    def __init__(self, fileobj, spacing: int = DEFAULT_CHECKPOINT_SPACING):
        super().__init__()
        self._f = fileobj
        self._spacing = int(spacing)
        self._chunk = min(_CHUNK, max(1024, self._spacing // 4))  # input granularity of checkpoints
        # checkpoints: parallel lists sorted by decompressed offset
        self._ck_out: list[int] = [0]
        self._ck_in: list[int] = [0]
        self._ck_dec: list[Any] = [zlib.decompressobj(31)]
        self._frontier = 0  # furthest decompressed offset reached
        self._end: int | None = None  # total decompressed size once known
        self._restore(0)
        self._pos = 0

    # -- decompressor state -------------------------------------------------------
    def _restore(self, k: int) -> None:
        self._dec = self._ck_dec[k].copy()
        self._in_pos = self._ck_in[k]
        self._f.seek(self._in_pos)
        self._tail = b""
        self._buf = b""
        self._buf_off = self._ck_out[k]  # decompressed offset of self._buf[0]
        self._done = False

    def _more(self) -> bool:
        """Decompress the next piece into self._buf (replacing it). False at end of stream."""
        out_off = self._buf_off + len(self._buf)
        while True:
            if self._done:
                return False
            if self._dec.eof:
                data = self._dec.unused_data + self._tail
                if not data:
                    data = self._f.read(self._chunk)
                    self._in_pos += len(data)
                if not data or not data.startswith(b"\x1f\x8b"):
                    # end of the last gzip member (trailing zero padding is ignored)
                    self._done = True
                    self._end = out_off
                    return False
                self._dec = zlib.decompressobj(31)  # next member of a multi-member gzip
                self._tail = data
            if self._tail:
                data, self._tail = self._tail, b""
            else:
                data = self._f.read(self._chunk)
                if not data:
                    raise _GzipIndexError(
                        f"truncated gzip stream (ends at compressed byte {self._in_pos}, "
                        f"decompressed byte {out_off})"
                    )
                self._in_pos += len(data)
            try:
                out = self._dec.decompress(data, _MAX_OUT)
            except zlib.error as exc:
                raise _GzipIndexError(
                    f"corrupt gzip data near compressed byte {self._in_pos} ({exc})"
                ) from None
            self._tail = self._dec.unconsumed_tail
            new_end = out_off + len(out)
            if new_end > self._frontier:
                self._frontier = new_end
                if (
                    not self._tail
                    and not self._dec.eof
                    and new_end - self._ck_out[-1] >= self._spacing
                ):
                    self._ck_out.append(new_end)
                    self._ck_in.append(self._in_pos)
                    self._ck_dec.append(self._dec.copy())
            if out:
                self._buf = out
                self._buf_off = out_off
                return True

    def _position(self, pos: int) -> None:
        """Make self._buf contain `pos` (or reach end of stream)."""
        buf_end = self._buf_off + len(self._buf)
        if self._buf_off <= pos < buf_end:
            return
        k = bisect_right(self._ck_out, pos) - 1
        if pos < self._buf_off or self._ck_out[k] > buf_end:
            self._restore(k)
        while not (self._buf_off <= pos < self._buf_off + len(self._buf)):
            if not self._more():
                return

    # -- io API ----------------------------------------------------------------------
    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = 0) -> int:
        if whence == 0:
            pos = offset
        elif whence == 1:
            pos = self._pos + offset
        else:
            if self._end is None:
                self._position(1 << 62)  # decompress to the end
            pos = (self._end or 0) + offset
        if pos < 0:
            raise ValueError("negative seek position")
        self._pos = pos
        return pos

    def read(self, n: int = -1) -> bytes:
        parts = []
        remaining = (1 << 62) if n is None or n < 0 else n
        while remaining > 0:
            self._position(self._pos)
            start = self._pos - self._buf_off
            if not (0 <= start < len(self._buf)):
                break  # end of stream
            piece = self._buf[start : start + remaining]
            parts.append(piece)
            self._pos += len(piece)
            remaining -= len(piece)
        return b"".join(parts)

    def readinto(self, b) -> int:
        data = self.read(len(b))
        b[: len(data)] = data
        return len(data)

    def read_to_end(self) -> int:
        """Decompress to the end of the stream (verifies the gzip CRC); returns its size."""
        self.seek(0, 2)
        return self._end or 0

    @property
    def n_checkpoints(self) -> int:
        return len(self._ck_out)


# --------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------


class Table:
    """A small column table: ``table["x"]`` is a numpy array, ``len(table)`` the row count,
    iterating gives the column names (as a pandas DataFrame does).

    Numeric columns are float64 (``frame`` is int64, ``enable`` bool); text columns
    are object arrays of str. ``table.row(i)`` gives one row as a dict.
    """

    def __init__(self, columns: dict[str, np.ndarray], name: str = ""):
        self._cols = dict(columns)
        self.name = name
        lengths = {len(v) for v in self._cols.values()}
        self._n = lengths.pop() if lengths else 0

    @property
    def columns(self) -> list[str]:
        return list(self._cols)

    def __getitem__(self, key: str) -> np.ndarray:
        try:
            return self._cols[key]
        except KeyError:
            raise MissingColumnError(f"{self.name or 'table'}: no column {key!r} (have {', '.join(self._cols) or 'none'})") from None

    def __iter__(self):
        return iter(self._cols)

    def __len__(self) -> int:
        return self._n

    def __contains__(self, key: object) -> bool:
        return key in self._cols

    def keys(self):
        return self._cols.keys()

    @property
    def n_rows(self) -> int:
        return self._n

    def row(self, i: int) -> dict[str, Any]:
        """Row `i` as a dict of Python scalars."""
        return {k: v[i].item() if isinstance(v[i], np.generic) else v[i] for k, v in self._cols.items()}

    def to_array(self, columns: Sequence[str]) -> np.ndarray:
        """(N, len(columns)) float64 array of the named numeric columns (ArchiveError naming
        the table, column and line when a column is missing or holds text)."""
        arrays = []
        for c in columns:
            col = self[c]
            if col.dtype == object:
                bad = next((i for i, v in enumerate(col) if not _is_float_text(v)), 0)
                raise ArchiveError(f"{self.name or 'table'}: column '{c}' holds text ({str(col[bad])[:40]!r} at line {bad + 2}), expected numbers")
            arrays.append(np.asarray(col, dtype=float))
        return np.stack(arrays, axis=1).reshape(self._n, len(columns)) if arrays else np.zeros((self._n, 0))

    def int_column(self, name: str) -> np.ndarray:
        """Column `name` as int64; ArchiveError naming the table and line when a value is
        missing, text, fractional or beyond +-2**53."""
        col = self[name]
        if col.dtype.kind in "iu":
            return col.astype(np.int64)
        out = np.empty(len(col), dtype=np.int64)
        for i, v in enumerate(col):
            try:
                out[i] = _parse_int(str(v))
            except ValueError:
                raise ArchiveError(f"{self.name or 'table'}: column '{name}' at line {i + 2}: {str(v)[:40]!r} is not an integer") from None
        return out

    def __repr__(self) -> str:
        return f"Table({self.name!r}, rows={self._n}, columns={self.columns})"


def _parse_float(text: str) -> float:
    t = text.strip()
    if t == "":
        return float("nan")  # pandas writes NaN as an empty field
    return float(t)


def _parse_bool(text: str) -> bool:
    t = text.strip().lower()
    if t in ("true", "1", "1.0", "yes"):
        return True
    if t in ("false", "0", "0.0", "no", ""):
        return False
    raise ValueError(f"not a boolean: {text!r}")


def _parse_int(text: str) -> int:
    v = float(text)
    if not np.isfinite(v) or v != int(v) or abs(v) > 2**53:
        raise ValueError(f"not an integer (or beyond +-2**53): {text!r}")
    return int(v)


def _is_float_text(v) -> bool:
    try:
        float(v)
    except (TypeError, ValueError):
        return False
    return True


def _utf8_lines(data: bytes, where: str):
    """Decoded lines of `data`, one at a time (no full-text copy: io.StringIO would hold 4
    bytes per character); a UTF-8 BOM is dropped; ArchiveError names the bad line."""
    for k, line in enumerate(io.BytesIO(data), start=1):
        if k == 1 and line.startswith(b"\xef\xbb\xbf"):
            line = line[3:]
        try:
            yield line.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ArchiveError(f"{where}: line {k}: not UTF-8 text (byte 0x{line[exc.start]:02x})") from None


def _csv_rows(data: bytes, where: str) -> list[list[str]]:
    """Non-blank CSV rows of `data` (UTF-8), blank lines skipped while reading (a member of a
    million newlines costs nothing), at most MAX_TABLE_CELLS cells, fields of at most
    MAX_CSV_FIELD characters."""
    rows: list[list[str]] = []
    cells = 0
    old = csv.field_size_limit(MAX_CSV_FIELD)
    reader = csv.reader(_utf8_lines(data, where))
    try:
        for r in reader:
            if not r:
                continue
            cells += len(r)
            if cells > MAX_TABLE_CELLS:
                raise LimitError(f"{where}: more than {MAX_TABLE_CELLS:,} cells (line {reader.line_num})")
            rows.append(r)
    except csv.Error as exc:
        msg = f"a field is longer than {MAX_CSV_FIELD:,} characters" if "field limit" in str(exc) else f"malformed CSV ({exc})"
        raise ArchiveError(f"{where}: line {reader.line_num}: {msg}") from None
    finally:
        csv.field_size_limit(old)
    return rows


def _parse_csv(
    data: bytes,
    where: str,
    *,
    required: Sequence[str] = (),
    ints: Sequence[str] = (),
    bools: Sequence[str] = (),
    floats: Sequence[str] = (),
    strings: Sequence[str] = (),
    allow_empty: bool = False,
) -> Table:
    """Parse CSV bytes into a Table. Columns not named are inferred (float, else str).

    `allow_empty`: a file without a header (pandas writes an empty DataFrame as ``"\\n"``,
    the 1-byte camera tables of older recorders) gives an empty Table instead of an error.
    Raises ArchiveError naming `where` (archive: member) on any problem.
    """
    rows = _csv_rows(data, where)  # decodes UTF-8 line by line, skips blank lines
    if not rows:
        if required and not allow_empty:
            raise ArchiveError(f"{where}: empty file, expected columns {', '.join(required)}")
        return Table({}, where)
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise ArchiveError(f"{where}: missing column(s) {', '.join(missing)}")
    body = rows[1:]
    for i, r in enumerate(body):
        if len(r) != len(header):
            raise ArchiveError(
                f"{where}: line {i + 2} has {len(r)} fields, header has {len(header)}"
            )
    cols: dict[str, np.ndarray] = {}
    for j, name in enumerate(header):
        raw = [r[j] for r in body]
        if name in strings:
            cols[name] = np.array(raw, dtype=object)
            continue
        parser, dtype = _parse_float, np.float64
        if name in ints:
            parser, dtype = _parse_int, np.int64
        elif name in bools:
            parser, dtype = _parse_bool, bool
        elif name not in floats:
            if raw and all(_INT_TEXT.match(v) for v in raw) and all(len(v.strip()) < 16 for v in raw):
                cols[name] = np.array([int(v) for v in raw], dtype=np.int64)  # inferred integer column
                continue
            try:  # inferred column: numeric if every value parses
                cols[name] = np.array([_parse_float(v) for v in raw], dtype=np.float64)
            except ValueError:
                cols[name] = np.array(raw, dtype=object)
            continue
        values = []
        for i, v in enumerate(raw):
            try:
                values.append(parser(v))
            except ValueError:
                raise ArchiveError(
                    f"{where}: malformed value {v!r} in column '{name}' at line {i + 2}"
                ) from None
        cols[name] = np.array(values, dtype=dtype)
    return Table(cols, where)


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

    def __init__(self, path: str | os.PathLike, *, checkpoint_spacing: int = DEFAULT_CHECKPOINT_SPACING):
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
            self.path, len(self._members), self._stream.n_checkpoints, time.perf_counter() - t0,
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
                    n[len(self._prefix) :]: m for n, m in self._members.items() if n.startswith(self._prefix)
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
            root = next((r for r in _CAMERA_ROOTS if f"{r}/{name}/{name}_frames.csv" in self._members), None)
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
            self._camera_tables[name] = table
            self._camera_index[name] = self._index_frames(table["frame"], member)
            self._check_images(name, table, member)

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
                        raise self._err("initial.toml", f"[cameras.{name}] {key} = {str(v)[:40]!r}: expected a positive integer (pixels)")
            for key in ("fov", "hfov_deg"):
                if key in cfg:
                    v = cfg[key]
                    try:
                        f = float(v) if not isinstance(v, bool) else float("nan")
                    except (TypeError, ValueError):
                        f = float("nan")
                    if not 0.0 < f < 180.0:
                        raise self._err("initial.toml", f"[cameras.{name}] {key} = {str(v)[:40]!r}: expected degrees in (0, 180)")

    def _index_frames(self, frames: np.ndarray, member: str) -> dict[int, int]:
        index: dict[int, int] = {}
        for i, f in enumerate(frames.tolist()):
            if f in index:
                raise self._err(member, f"frame {f} appears twice (lines {index[f] + 2} and {i + 2})")
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
            other = next((f"{r}/{camera}/{kind}/{fname}" for r in _CAMERA_ROOTS if r != root), member)
            if other in self._members:
                return other
        return member

    # -- initial.toml ----------------------------------------------------------------
    def _number(self, value: Any, key: str, kind: type = float) -> Any:
        """A TOML number, or a number stored as a string (older recorder generations: the
        ``toml`` package writes numpy scalars as strings, e.g. ``"1.5"`` or ``"np.float64(1.5)"``)."""
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
                raise self._err("initial.toml", f"'{key}' must be [x, y, z, roll, pitch, yaw], got {v!r}")
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
            out["lander"] = [float(v) for v in matrix_to_pose(invert_transform(T_map_rover) @ T_map_lander)]
        return out

    @property
    def lander_stored_in_map_frame(self) -> bool:
        """True for archives lunarloc wrote before :data:`DATA_SPEC` (``data_spec`` in
        :data:`LEGACY_MAP_LANDER_SPECS`), whose initial.toml ``lander`` is a map-frame pose.
        ``initial["lander"]`` is rover-relative either way (``initial_raw`` keeps the text)."""
        return str(self.metadata.get("data_spec", "")) in LEGACY_MAP_LANDER_SPECS

    def initial_rover_pose(self) -> np.ndarray:
        """``T_map_rover`` (4x4) at the start: initial.toml ``rover`` (LAC ``get_initial_position``)."""
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
        limit = MAX_TOML_BYTES if name.endswith(".toml") else MAX_TABLE_BYTES if name.endswith(".csv") else MAX_IMAGE_BYTES
        if info.size > limit:
            raise self._err(name, f"member is {info.size:,} bytes, over the {limit:,}-byte limit for this kind of member")
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
        raise InputError(f"{self.path}: no camera named {camera!r} (have {', '.join(self.initial['cameras'])})")

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
            raise self._err(member, f"no custom record {name!r} (have: {', '.join(self.custom_records) or 'none'})")
        return _parse_csv(self._read_member(member), f"{self.path}: {member}")

    def has_member(self, name: str) -> bool:
        return name in self._members

    @property
    def member_names(self) -> list[str]:
        return list(self._members)

    # -- images ----------------------------------------------------------------------
    def image_member(self, camera: str, frame: int, kind: str = "grayscale") -> str | None:
        """Archive member path of an image, or None when that camera has no such image at `frame`."""
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
                    raise self._err(member, f"image is {w}x{h} pixels, over the {MAX_IMAGE_PIXELS:,}-pixel limit")
                return np.array(img)
        except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
            if isinstance(exc, ArchiveError):
                raise
            raise self._err(member, f"cannot decode image ({exc})") from None

    def image(self, camera: str, frame: int, kind: str = "grayscale") -> np.ndarray | None:
        """Image of `camera` at `frame`: grayscale (H, W) uint8, semantic (H, W[, 3]); None if absent."""
        member = self.image_member(camera, frame, kind)
        return None if member is None else self.read_image(member)

    def grayscale(self, camera: str, frame: int) -> np.ndarray | None:
        """(H, W) uint8 grayscale image of `camera` at `frame`, or None if none was recorded."""
        return self.image(camera, frame, "grayscale")

    def semantic(self, camera: str, frame: int) -> np.ndarray | None:
        """Semantic image of `camera` at `frame` ((H, W) or (H, W, 3)), or None."""
        return self.image(camera, frame, "semantic")

    def read_images(self, requests: Sequence[tuple[str, int, str]]) -> dict[tuple[str, int, str], np.ndarray]:
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
        """(N, 3) ground-truth rover positions from frames.csv, metres."""
        return self.frames.to_array(("x", "y", "z"))

    def poses(self) -> np.ndarray:
        """(N, 6) rover poses [x, y, z, roll, pitch, yaw] from frames.csv."""
        return self.frames.to_array(("x", "y", "z", "roll", "pitch", "yaw"))

    def path_length(self) -> float:
        """Length of the ground-truth path, metres (sum of 3D steps between frames)."""
        p = self.positions()
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0

    def duration(self) -> float:
        """Mission time spanned by frames.csv, seconds."""
        t = self.frames["mission_time"]
        return float(np.nanmax(t) - np.nanmin(t)) if len(t) else 0.0


# --------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------


def _fmt(v: Any) -> str:
    """CSV text of one value: floats by :func:`float_text`, ints as ints, bools as True/False."""
    if isinstance(v, (bool, np.bool_)):
        return "True" if v else "False"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return float_text(v)
    return str(v)


def _pandas_exact(text: str) -> bool:
    """True when pandas' default C float parser (``precise_xstrtod``, pandas 2.x) reads
    `text` as the correctly rounded double, i.e. the value Python's ``float`` reads.

    That parser accumulates up to 17 digits (leading zeros included) into a double and
    then multiplies or divides once by a power of ten from a table: exact when the digit
    string is below 2**53 and the power is an exact double (10**0 .. 10**22).
    """
    mant, _, ex = text.partition("e")
    mant = mant.lstrip("+-")
    whole, _, frac = mant.partition(".")
    digits = whole + frac
    try:
        exponent = int(ex or 0) - len(frac)
    except ValueError:
        return False
    return digits.isdigit() and len(digits) <= 17 and int(digits) < 2**53 and -22 <= exponent <= 22


def float_text(value: float) -> str:
    """CSV text of a float that Python's ``float`` and pandas' default parser read identically.

    The shortest round-trip ``repr`` when pandas reads it exactly (most values: the value
    round-trips bit-exact); otherwise the value rounded to 15 significant digits (fewer
    below 1e-7, so the decimal exponent stays within pandas' exact range), a relative change
    below 5e-15 and an absolute one below 1e-22. NaN is written as an empty field (pandas'
    spelling). Measured with pandas 2.2.3: 0 of 127,006 random values read back differently
    (the plain ``repr`` gave 33,780 of 76,000).
    """
    f = float(value)
    if math.isnan(f):
        return ""
    if math.isinf(f) or f == 0.0:
        return repr(f)
    text = repr(f)
    if _pandas_exact(text):
        return text
    n = min(15, 23 + math.floor(math.log10(abs(f))))
    if n < 1:
        return "0.0"  # |value| < 1e-22
    g = float(f"{f:.{n}g}")
    text = repr(g)
    if _pandas_exact(text):
        return text
    mant, _, ex = f"{g:.{n - 1}e}".partition("e")
    if "." in mant:
        mant = mant.rstrip("0").rstrip(".")
    return f"{mant}e{ex}"


def lander_pose_map(initial: dict) -> list[float]:
    """Map-frame lander pose [x, y, z, roll, pitch, yaw] from an initial.toml dict whose
    ``lander`` is relative to the rover and ``rover`` is the rover's map-frame pose:
    ``T_map_lander = T_map_rover @ T_rover_lander``."""
    from lunarloc.core.geometry import matrix_to_pose, pose_to_matrix

    T = pose_to_matrix(*(float(v) for v in initial["rover"])) @ pose_to_matrix(*(float(v) for v in initial["lander"]))
    return [float(v) for v in matrix_to_pose(T)]


def lander_pose_relative(rover_pose_map, lander_pose_map_) -> list[float]:
    """The rover-relative lander pose initial.toml stores (LAC ``get_initial_lander_position``)
    from map-frame rover and lander poses: ``T_rover_lander = T_map_rover^-1 @ T_map_lander``."""
    from lunarloc.core.geometry import invert_transform, matrix_to_pose, pose_to_matrix

    T_map_rover = pose_to_matrix(*(float(v) for v in rover_pose_map))
    T_map_lander = pose_to_matrix(*(float(v) for v in lander_pose_map_))
    return [float(v) for v in matrix_to_pose(invert_transform(T_map_rover) @ T_map_lander)]


def _to_toml_value(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _to_toml_value(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_to_toml_value(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
    if isinstance(v, (np.bool_,)):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    if v is None:
        raise InputError("initial.toml values cannot be None")
    return v


class LacWriter:
    """Write a `.lac` archive that the LAC's published reader (and :class:`LacArchive`) reads.

    Images are PNG-encoded and streamed into the (temporary) archive as they are
    added; tables are buffered and written on :meth:`close`, which also fills
    metadata.toml and atomically renames the temporary file to `path`. If the
    ``with`` block raises, the temporary file is removed and `path` is untouched.

    Parameters
    ----------
    path : output `.lac` file (parent folder is created).
    initial : dict for initial.toml: ``fiducials`` (bool), ``rover`` (map-frame pose) and
        ``lander`` (pose *relative to the rover*, as the LAC's ``get_initial_lander_position``
        returns it; see :func:`lander_pose_relative`), both [x, y, z, roll, pitch, yaw] in m
        and rad, ``cameras`` ({Name: {camera_active, light_intensity, width, height,
        use_semantic}}).
    description : free text stored in metadata.toml.
    data_spec : format tag stored in metadata.toml (:data:`DATA_SPEC`; the legacy tags of
        :data:`LEGACY_MAP_LANDER_SPECS` are refused: readers would take ``lander`` as map-frame).
    compresslevel : gzip level 0-9 (PNG data barely compresses; 1 is fastest).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        initial: dict,
        description: str = "",
        data_spec: str = DATA_SPEC,
        *,
        compresslevel: int = 1,
        png_compress_level: int = 3,
    ):
        self.path = Path(path)
        if str(data_spec) in LEGACY_MAP_LANDER_SPECS:
            raise InputError(f"data_spec {data_spec!r} marks a map-frame lander; this writer stores it rover-relative")
        missing = [k for k in ("lander", "rover", "cameras") if k not in initial]
        if missing:
            raise InputError(f"initial dict lacks {', '.join(missing)}")
        self.initial = _to_toml_value(dict(initial))
        self.initial.setdefault("fiducials", False)
        for key in ("lander", "rover"):
            if len(self.initial[key]) != 6:
                raise InputError(f"initial['{key}'] must be [x, y, z, roll, pitch, yaw]")
            # all floats: the `toml` package of the published reader rejects mixed int/float arrays
            self.initial[key] = [float(v) for v in self.initial[key]]
        cams = self.initial["cameras"]
        if not isinstance(cams, dict):
            raise InputError("initial['cameras'] must be a dict {name: config}")
        for name, cfg in cams.items():
            if not _CAMERA_NAME.match(name):
                raise InputError(f"invalid camera name {name!r}")
            for k, default in (("camera_active", False), ("light_intensity", 0.0), ("use_semantic", False)):
                cfg.setdefault(k, default)
        self.metadata = {
            "data_spec": str(data_spec),
            "description": str(description),
            "start_time": datetime.now().strftime(_TIME_FORMAT),
            "end_time": "",
            "frames": 0,
        }
        self._png_level = int(png_compress_level)
        self._frames: list[list[str]] = []
        self._last_frame: int | None = None
        self._camera_rows: dict[str, list[list[str]]] = {name: [] for name in cams}
        self._camera_last: dict[str, int] = {}
        self._custom: dict[str, tuple[list[str], list[list[str]]]] = {}
        self._closed = False
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        os.close(fd)
        self._tmp = Path(tmp)
        try:
            self._tar = tarfile.open(self._tmp, mode="w:gz", compresslevel=int(compresslevel), format=tarfile.PAX_FORMAT)
            import tomli_w

            self._toml = tomli_w
            self._add_bytes("initial.toml", tomli_w.dumps(self.initial).encode("utf-8"))
            self._add_bytes(".gitignore", b"*\n")
        except BaseException:
            self._discard()
            raise

    # -- low level -------------------------------------------------------------------
    def _add_bytes(self, name: str, data: bytes) -> None:
        info = tarfile.TarInfo(name=name)
        info.size = len(data)
        info.mtime = int(time.time())
        info.mode = 0o644
        self._tar.addfile(info, io.BytesIO(data))

    def _check_open(self) -> None:
        if self._closed:
            raise InputError(f"{self.path}: writer is closed")

    def _encode_png(self, image: np.ndarray, what: str, *, allow_rgb: bool) -> bytes:
        from PIL import Image

        arr = np.asarray(image)
        ok_gray = arr.ndim == 2 and arr.dtype in (np.uint8, np.uint16)
        ok_rgb = allow_rgb and arr.ndim == 3 and arr.shape[2] == 3 and arr.dtype == np.uint8
        if not allow_rgb and arr.dtype == np.uint16:
            ok_gray = False
        if not (ok_gray or ok_rgb):
            allowed = "(H, W) uint8/uint16 or (H, W, 3) uint8" if allow_rgb else "(H, W) uint8"
            raise InputError(f"{what} must be {allowed}, got shape {arr.shape} dtype {arr.dtype}")
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(arr)).save(buf, format="PNG", compress_level=self._png_level)
        return buf.getvalue()

    # -- public API ------------------------------------------------------------------
    def add_frame(self, frame: int, **state: float) -> None:
        """Add one frames.csv row. `state` keys are :data:`STATE_COLUMNS`; missing ones are 0.0.

        Frame numbers must increase strictly.
        """
        self._check_open()
        unknown = sorted(set(state) - set(STATE_COLUMNS))
        if unknown:
            raise InputError(f"unknown frame state key(s) {', '.join(unknown)}; allowed: {', '.join(STATE_COLUMNS)}")
        frame = int(frame)
        if self._last_frame is not None and frame <= self._last_frame:
            raise InputError(f"frame {frame} added after frame {self._last_frame}; frames must increase")
        self._last_frame = frame
        row = [str(frame)]
        for col in STATE_COLUMNS:
            row.append(_fmt(float(state.get(col, 0.0))))
        self._frames.append(row)

    def add_camera_frame(
        self,
        camera: str,
        frame: int,
        pose_xyzrpy: Sequence[float],
        *,
        enable: bool = True,
        light_intensity: float = 0.0,
        grayscale: np.ndarray | None = None,
        semantic: np.ndarray | None = None,
    ) -> None:
        """Add one camera-table row and stream its images into the archive.

        Parameters
        ----------
        camera : a camera named in ``initial["cameras"]``.
        frame : frame number (strictly increasing per camera).
        pose_xyzrpy : camera pose relative to the rover [x, y, z, roll, pitch, yaw] (m, rad).
        enable : camera on/off; an enabled row needs a grayscale image (as in the LAC).
        light_intensity : lamp intensity, 0-1.
        grayscale : (H, W) uint8 image (H, W must match the camera config when given).
        semantic : (H, W) uint8/uint16 or (H, W, 3) uint8; required with grayscale when the
            camera has ``use_semantic``, refused otherwise.
        """
        self._check_open()
        cfg = self.initial["cameras"].get(camera)
        if cfg is None:
            raise InputError(f"camera {camera!r} is not in initial['cameras'] ({', '.join(self.initial['cameras'])})")
        frame = int(frame)
        last = self._camera_last.get(camera)
        if last is not None and frame <= last:
            raise InputError(f"{camera}: frame {frame} added after frame {last}; frames must increase")
        pose = [float(v) for v in pose_xyzrpy]
        if len(pose) != 6:
            raise InputError(f"{camera}: pose_xyzrpy must have 6 values, got {len(pose)}")
        if grayscale is None and enable:
            raise InputError(f"{camera} frame {frame}: an enabled camera row needs a grayscale image")
        use_sem = bool(cfg.get("use_semantic", False))
        if semantic is not None and not use_sem:
            raise InputError(f"{camera}: semantic image given but use_semantic is false in initial['cameras']")
        if use_sem and grayscale is not None and semantic is None:
            raise InputError(f"{camera} frame {frame}: use_semantic is true, a semantic image is required")
        names = {"grayscale": "", "semantic": ""}
        for kind, img in (("grayscale", grayscale), ("semantic", semantic)):
            if img is None:
                continue
            arr = np.asarray(img)
            self._check_size(camera, cfg, arr, kind)
            data = self._encode_png(arr, f"{camera} {kind} image", allow_rgb=(kind == "semantic"))
            fname = f"{camera}_{kind}_{frame}.png"
            self._add_bytes(f"cameras/{camera}/{kind}/{fname}", data)
            names[kind] = fname
        self._camera_last[camera] = frame
        self._camera_rows[camera].append(
            [str(frame), _fmt(bool(enable)), *(_fmt(v) for v in pose), _fmt(float(light_intensity)),
             names["grayscale"], names["semantic"]]
        )  # fmt: skip

    @staticmethod
    def _check_size(camera: str, cfg: dict, arr: np.ndarray, kind: str) -> None:
        try:
            w, h = int(cfg.get("width", 0)), int(cfg.get("height", 0))
        except (TypeError, ValueError):
            return
        if w and h and arr.shape[:2] != (h, w):
            raise InputError(f"{camera} {kind} image is {arr.shape[1]}x{arr.shape[0]}, camera config says {w}x{h}")

    def add_custom(self, name: str, columns: Sequence[str], rows: np.ndarray | Sequence[Sequence]) -> None:
        """Add the custom record ``custom/<name>.csv`` (written on close).

        `columns` are the header; `rows` a 2-D array or a sequence of rows (numbers or text).
        """
        self._check_open()
        if not _RECORD_NAME.match(name):
            raise InputError(f"custom record name {name!r} must match [A-Za-z0-9_-]+")
        if name in self._custom:
            raise InputError(f"custom record {name!r} already added")
        columns = [str(c) for c in columns]
        out_rows = []
        for i, r in enumerate(rows):
            values = list(r.tolist() if isinstance(r, np.ndarray) else r)
            if len(values) != len(columns):
                raise InputError(f"custom record {name!r}: row {i} has {len(values)} values for {len(columns)} columns")
            out_rows.append([_fmt(v) for v in values])
        self._custom[name] = (columns, out_rows)

    @staticmethod
    def _csv_bytes(header: Sequence[str], rows: Sequence[Sequence[str]]) -> bytes:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)
        return buf.getvalue().encode("utf-8")

    def close(self) -> Path:
        """Write tables and metadata, close the tar, rename into place; returns the path."""
        if self._closed:
            return self.path
        try:
            self.metadata["end_time"] = datetime.now().strftime(_TIME_FORMAT)
            self.metadata["frames"] = len(self._frames)
            self._add_bytes("metadata.toml", self._toml.dumps(self.metadata).encode("utf-8"))
            self._add_bytes("frames.csv", self._csv_bytes(FRAME_COLUMNS, self._frames))
            known = {int(r[0]) for r in self._frames}
            for cam, rows in self._camera_rows.items():
                if not rows:
                    continue  # as the LAC recorder: no table for a camera that recorded nothing
                orphans = [r[0] for r in rows if int(r[0]) not in known]
                if orphans:
                    logger.warning("%s: %d %s frames are not in frames.csv (first %s)", self.path, len(orphans), cam, orphans[0])
                self._add_bytes(f"cameras/{cam}/{cam}_frames.csv", self._csv_bytes(CAMERA_COLUMNS, rows))
            for name, (cols, rows) in self._custom.items():
                self._add_bytes(f"custom/{name}.csv", self._csv_bytes(cols, rows))
            self._tar.close()
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(self._tmp, 0o666 & ~umask)  # mkstemp creates 0600
            os.replace(self._tmp, self.path)
        except BaseException:
            self._discard()
            raise
        self._closed = True
        logger.info("wrote %s (%d frames)", self.path, len(self._frames))
        return self.path

    def _discard(self) -> None:
        self._closed = True
        tar = getattr(self, "_tar", None)
        if tar is not None:
            try:
                tar.close()
            except Exception:  # noqa: BLE001 - best effort cleanup
                pass
        try:
            self._tmp.unlink()
        except FileNotFoundError:
            pass

    def abort(self) -> None:
        """Discard everything written so far (the target path is not touched)."""
        if not self._closed:
            self._discard()

    def __enter__(self) -> LacWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
