"""Seekable view of a gzip file: one pass builds an index of decompressor checkpoints, so a
`.lac` archive's members can be read in any order without decompressing from the start."""

from __future__ import annotations

import io
import zlib
from bisect import bisect_right
from typing import Any


_CHUNK = 256 * 1024  # compressed bytes read per step
_MAX_OUT = 1024 * 1024  # cap on decompressed bytes per zlib call (bounds memory)
DEFAULT_CHECKPOINT_SPACING = 4 * 1024 * 1024  # decompressed bytes between checkpoints


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
