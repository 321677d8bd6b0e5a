"""Safe reading of input files: existence and type checks, size limits checked before
reading, text decoding with one-line errors, and `.npz` arrays checked before loading.

Every limit below is stated (and measured) in ``docs/robustness.md``. They bound the
memory a hostile file can make lunarloc allocate; honest inputs are far below them
(the largest real LunarLoc traverse CSV is 2.9 MB with a 850-character boulder field).
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
import stat
import zipfile
from pathlib import Path

import numpy as np

from lunarloc.core.errors import (
    FileFormatError,
    LimitError,
    NotAFileError,
    UnreadableFileError,
    file_error,
)

__all__ = [
    "MAX_CSV_BYTES",
    "MAX_CSV_FIELD_CHARS",
    "MAX_CSV_ROWS",
    "MAX_NPZ_MEMBER_BYTES",
    "MAX_NPZ_MEMBERS",
    "MAX_ABS_COORD_M",
    "check_input_file",
    "open_text",
    "decode_error",
    "csv_field_limit",
    "load_npz_arrays",
]

MAX_CSV_BYTES = 512 * 1024**2
"""A CSV input (traverse, landmark map, rock list) larger than this is refused before reading."""
MAX_CSV_FIELD_CHARS = 8 * 1024**2
"""Longest CSV field accepted (Python's csv default is 131,072; a frame with 6,000 rocks
needs ~360,000 characters; 8 Mi characters hold ~130,000 rocks)."""
MAX_CSV_ROWS = 10_000_000
"""Most data rows read from one CSV (a 20 Hz traverse of 5.8 days)."""
MAX_NPZ_MEMBER_BYTES = 512 * 1024**2
"""Largest uncompressed array in a `.npz` map (21 M landmarks as float64 x, y, z)."""
MAX_NPZ_MEMBERS = 64
"""Most arrays in one `.npz` map."""
MAX_ABS_COORD_M = 1.0e7
"""Landmark and pose coordinates beyond +-10,000 km (several Moon radii) are refused as absurd."""


def check_input_file(
    path: str | os.PathLike, max_bytes: int | None = None, what: str = "input"
) -> Path:
    """Return `path` as a Path after checking that it is a readable regular file no larger
    than `max_bytes`; raises MissingFileError, NotAFileError, UnreadableFileError or LimitError."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError as exc:
        raise file_error(p, exc) from None
    if stat.S_ISDIR(st.st_mode):
        raise NotAFileError(f"{p}: is a folder, expected a {what} file")
    if not stat.S_ISREG(st.st_mode):
        raise NotAFileError(
            f"{p}: not a regular file (a device, pipe or socket), expected a {what} file"
        )
    if not os.access(p, os.R_OK):
        raise UnreadableFileError(f"{p}: permission denied (read)")
    if max_bytes is not None and st.st_size > max_bytes:
        raise LimitError(
            f"{p}: {st.st_size / 1024**2:.0f} MiB is over the {max_bytes / 1024**2:.0f} MiB limit "
            f"for a {what} file"
        )
    return p


_BOMS = (
    (b"\xff\xfe\x00\x00", "UTF-32"),
    (b"\x00\x00\xfe\xff", "UTF-32"),
    (b"\xff\xfe", "UTF-16"),
    (b"\xfe\xff", "UTF-16"),
)


def open_text(path: str | os.PathLike, max_bytes: int = MAX_CSV_BYTES, what: str = "CSV"):
    """Open a UTF-8 text file for streaming (``newline=""`` for the csv module) after the
    checks of :func:`check_input_file`; a UTF-16/32 file is refused with a one-line hint.
    Decoding errors surface while reading as UnicodeDecodeError: turn them into our error
    with :func:`decode_error`."""
    p = check_input_file(path, max_bytes, what)
    try:
        with open(p, "rb") as fh:
            head = fh.read(4)
        for bom, name in _BOMS:
            if head.startswith(bom):
                raise FileFormatError(
                    f"{p}: {name} text; lunarloc reads UTF-8 (save the file as UTF-8)"
                )
        if head[:2].count(0) and len(head) >= 2:
            raise FileFormatError(
                f"{p}: binary data or UTF-16 text without a byte-order mark; expected UTF-8 {what}"
            )
        return open(p, encoding="utf-8-sig", newline="")  # noqa: SIM115 - the caller closes it
    except OSError as exc:
        raise file_error(p, exc) from None


def decode_error(path, exc: UnicodeDecodeError, line: int | None = None) -> FileFormatError:
    """One-line error for a decoding failure at (about) `line`."""
    where = f"{path}:{line}" if line else f"{path}"
    return FileFormatError(
        f"{where}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x}); save the file as UTF-8"
    )


@contextlib.contextmanager
def csv_field_limit(limit: int = MAX_CSV_FIELD_CHARS):
    """Raise the csv module's field size limit to `limit` characters for the block (the
    default 131,072 rejects real frames with thousands of rocks), restoring it afterwards."""
    old = csv.field_size_limit()
    csv.field_size_limit(limit)
    try:
        yield
    finally:
        csv.field_size_limit(old)


def csv_error(path, line: int, exc: csv.Error) -> FileFormatError:
    """One-line error for a csv module error (e.g. a field over the limit) at `line`."""
    msg = str(exc)
    if "field larger than field limit" in msg:
        return LimitError(
            f"{path}:{line}: a field is longer than the {MAX_CSV_FIELD_CHARS:,} character limit"
        )
    return FileFormatError(f"{path}:{line}: malformed CSV ({msg})")


_REAL_KINDS = "fiub"  # float, signed int, unsigned int, bool


def load_npz_arrays(
    path: str | os.PathLike, max_member_bytes: int | None = None
) -> dict[str, np.ndarray]:
    """All arrays of an `.npz` file, each checked before it is allocated: the file must be a
    zip of ``.npy`` members (at most :data:`MAX_NPZ_MEMBERS`), each header must declare a
    real (float, int, bool) or string dtype, a shape whose byte size is within
    `max_member_bytes` and equal to the member's uncompressed size (a compression bomb or
    a header lying about its shape is refused without decompressing it). Pickles are
    never loaded. Raises FileFormatError / LimitError naming the file and member.
    `max_member_bytes` defaults to :data:`MAX_NPZ_MEMBER_BYTES`."""
    max_member_bytes = MAX_NPZ_MEMBER_BYTES if max_member_bytes is None else max_member_bytes
    p = check_input_file(path, None, ".npz")
    if p.stat().st_size == 0:
        raise FileFormatError(f"{p}: empty file, expected a .npz archive")
    try:
        if not zipfile.is_zipfile(p):
            with open(p, "rb") as fh:
                magic = fh.read(6)
            kind = "a single .npy array" if magic == b"\x93NUMPY" else "not a zip archive"
            raise FileFormatError(f"{p}: not a .npz archive ({kind})")
        out: dict[str, np.ndarray] = {}
        with zipfile.ZipFile(p) as zf:
            infos = zf.infolist()
            if len(infos) > MAX_NPZ_MEMBERS:
                raise LimitError(f"{p}: {len(infos)} members, over the limit of {MAX_NPZ_MEMBERS}")
            for info in infos:
                name = info.filename
                if not name.endswith(".npy"):
                    raise FileFormatError(f"{p}: member {name!r} is not a .npy array")
                if info.file_size > max_member_bytes:
                    raise LimitError(
                        f"{p}: member {name} is {info.file_size / 1024**2:.0f} MiB uncompressed, "
                        f"over the {max_member_bytes / 1024**2:.0f} MiB limit"
                    )
                out[name[:-4]] = _read_npy_member(p, zf, info, max_member_bytes)
        return out
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        EOFError,
        ValueError,
        OSError,
        NotImplementedError,
        RuntimeError,
    ) as exc:  # zipfile: unsupported compression/encryption flags, passwords
        if isinstance(exc, (FileFormatError, LimitError)):
            raise
        if isinstance(exc, OSError) and exc.errno is not None:
            raise file_error(p, exc) from None
        raise FileFormatError(
            f"{p}: corrupt or truncated .npz archive ({type(exc).__name__}: {exc})"
        ) from None


def _read_npy_member(
    p: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo, max_bytes: int
) -> np.ndarray:
    name = info.filename
    with zf.open(info) as fh:
        try:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version in ((2, 0), (3, 0)):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                raise ValueError(f"unsupported .npy version {version}")
        except ValueError as exc:
            raise FileFormatError(f"{p}: member {name}: bad .npy header ({exc})") from None
        if dtype.hasobject or dtype.kind not in _REAL_KINDS + "U":
            raise FileFormatError(
                f"{p}: member {name}: dtype {dtype} is not allowed (real numbers or text only; "
                "complex values would lose their imaginary part)"
            )
        nbytes = math.prod(shape) * dtype.itemsize
        header_len = fh.tell()
        if nbytes > max_bytes:
            raise LimitError(
                f"{p}: member {name} declares shape {shape} ({nbytes / 1024**3:.1f} GiB), over the "
                "limit"
            )
        if nbytes + header_len != info.file_size:
            raise FileFormatError(
                f"{p}: member {name} declares shape {shape} {dtype} ({nbytes} bytes) but holds "
                f"{info.file_size - header_len} bytes"
            )
        data = fh.read(nbytes)
    if len(data) != nbytes:
        raise FileFormatError(f"{p}: member {name} is truncated")
    arr = np.frombuffer(data, dtype=dtype)
    if fortran:
        return arr.reshape(shape[::-1]).T.copy()
    return arr.reshape(shape).copy()
