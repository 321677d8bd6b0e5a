"""The CSV tables of a `.lac` archive (frames.csv, camera tables, custom records): bounded,
checked parsing into :class:`Table` with one-line errors naming the member and line."""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from lunarloc.core.errors import ArchiveError, LimitError, MissingColumnError

MAX_CSV_FIELD = 1024**2  # characters in one CSV field of an archive table
# rows x columns of one CSV member (frames.csv: 18 columns, 277 k rows = 3.9 h at 20 Hz)
MAX_TABLE_CELLS = 5_000_000
_INT_TEXT = re.compile(r"^\s*[-+]?\d+\s*$")


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
            raise MissingColumnError(
                f"{self.name or 'table'}: no column {key!r} (have "
                f"{', '.join(self._cols) or 'none'})"
            ) from None

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
        return {
            k: v[i].item() if isinstance(v[i], np.generic) else v[i] for k, v in self._cols.items()
        }

    def to_array(self, columns: Sequence[str]) -> np.ndarray:
        """(N, len(columns)) float64 array of the named numeric columns (ArchiveError naming
        the table, column and line when a column is missing or holds text)."""
        arrays = []
        for c in columns:
            col = self[c]
            if col.dtype == object:
                bad = next((i for i, v in enumerate(col) if not _is_float_text(v)), 0)
                raise ArchiveError(
                    f"{self.name or 'table'}: column '{c}' holds text ({str(col[bad])[:40]!r} at "
                    f"line {bad + 2}), expected numbers"
                )
            arrays.append(np.asarray(col, dtype=float))
        return (
            np.stack(arrays, axis=1).reshape(self._n, len(columns))
            if arrays
            else np.zeros((self._n, 0))
        )

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
                raise ArchiveError(
                    f"{self.name or 'table'}: column '{name}' at line {i + 2}: {str(v)[:40]!r} is "
                    "not an integer"
                ) from None
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
            raise ArchiveError(
                f"{where}: line {k}: not UTF-8 text (byte 0x{line[exc.start]:02x})"
            ) from None


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
                raise LimitError(
                    f"{where}: more than {MAX_TABLE_CELLS:,} cells (line {reader.line_num})"
                )
            rows.append(r)
    except csv.Error as exc:
        msg = (
            f"a field is longer than {MAX_CSV_FIELD:,} characters"
            if "field limit" in str(exc)
            else f"malformed CSV ({exc})"
        )
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
            if (
                raw
                and all(_INT_TEXT.match(v) for v in raw)
                and all(len(v.strip()) < 16 for v in raw)
            ):
                # inferred integer column
                cols[name] = np.array([int(v) for v in raw], dtype=np.int64)
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
