"""Checks of what the public API is given, as strict as the CLI's checks of its options:
rigid transforms, numbers within physical bounds, configs of the right type, images of the
right container. Every refusal is an :class:`~lunarloc.core.errors.InputError`
(values) or :class:`~lunarloc.core.errors.ConfigError` (configs) whose message starts with
the argument's name; a check returns the value it accepted (as float / ndarray) and changes
nothing else, so a caller that checks before touching its state leaves that state unchanged.

What is accepted (see docs/robustness.md, "The public API"):

* a **rigid transform**: a finite 4x4 whose rotation block R has ``max|R^T R - I| <=
  RIGID_TOL`` and ``|det R - 1| <= RIGID_TOL`` (1e-4: float32 poses, ~1e-7 off, pass; a 0.1 %
  scale, a reflection or a shear do not), last row ``0 0 0 1`` within 1e-9, translation
  within ``MAX_ABS_COORD_M`` (1e7 m, the landmark maps' limit);
* **speeds**: ``|linear| <= MAX_LINEAR_SPEED_MPS`` (0.98 m/s) and ``|angular| <=
  MAX_ANGULAR_SPEED_RADPS`` (8.26 rad/s): twice the LAC rover's limits (0.49 m/s, 4.13
  rad/s), so measurement noise around the limit passes and a value no rover reaches does not;
* **IMU** ``[ax, ay, az, wx, wy, wz]``: accelerations within ``MAX_ACCEL_MPS2`` (100 m/s^2,
  about 10 g: the LAC's IMU is a second difference of 20 Hz positions, a bump gives a few
  m/s^2) and rates within ``MAX_GYRO_RADPS`` (50 rad/s: a rover turning half a turn in one
  20 Hz tick);
* **mission time** in ``[0, MAX_MISSION_TIME_S]`` (1e7 s, 116 days; the LAC's clock starts at 0);
* numbers are ``int``/``float``/numpy scalars, never ``bool`` (``True`` is not 1 m/s);
* an **image** is a uint8 ndarray of the rig's (height, width), as the LAC gives it.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from lunarloc.core.errors import ConfigError, InputError

__all__ = [
    "API_WORDING",
    "LAC_MAX_ANGULAR_SPEED_RADPS",
    "LAC_MAX_LINEAR_SPEED_MPS",
    "MAX_ABS_COORD_M",
    "MAX_ACCEL_MPS2",
    "MAX_ANGULAR_SPEED_RADPS",
    "MAX_GYRO_RADPS",
    "MAX_LINEAR_SPEED_MPS",
    "MAX_MISSION_TIME_S",
    "OPTION_WORDING",
    "RIGID_TOL",
    "Wording",
    "gray_image",
    "imu_sample",
    "instance",
    "integer",
    "real",
    "rigid_transform",
]

RIGID_TOL = 1e-4
MAX_ABS_COORD_M = 1e7
LAC_MAX_LINEAR_SPEED_MPS = 0.49
LAC_MAX_ANGULAR_SPEED_RADPS = 4.13
MAX_LINEAR_SPEED_MPS = 2 * LAC_MAX_LINEAR_SPEED_MPS
MAX_ANGULAR_SPEED_RADPS = 2 * LAC_MAX_ANGULAR_SPEED_RADPS
MAX_ACCEL_MPS2 = 100.0
MAX_GYRO_RADPS = 50.0
MAX_MISSION_TIME_S = 1e7


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _fmt(a) -> str:
    return "[" + ", ".join(f"{float(x):.4g}" for x in np.ravel(a)) + "]"


@dataclass(frozen=True)
class Wording:
    """How :func:`real` words a refusal: the API's (``x must be >= 0 m, got -1``, ``x is not
    finite (nan)``) or a command-line option's (``--x must be >= 0 m; got -1``, ``--x must be a
    finite number; got nan``, the CLI's :func:`lunarloc.cli.checks.number`)."""

    got: str  # between the rule and the value refused
    not_finite: str  # the whole message for NaN / inf, with {name} and {value}


API_WORDING = Wording(", got", "{name} is not finite ({value})")
OPTION_WORDING = Wording("; got", "{name} must be a finite number; got {value}")


def real(
    value,
    name: str,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
    error: type = InputError,
    wording: Wording = API_WORDING,
) -> float:
    """`value` as a finite float within [lo, hi] (an end excluded with lo_open / hi_open); bools,
    strings and None refused, with `error` worded as `wording` says."""
    u = f" {unit}" if unit else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise error(
            f"{name} must be a number{u and ' in' + u}, got {type(value).__name__} {_short(value)}"
        )
    v = float(value)
    if not math.isfinite(v):
        raise error(wording.not_finite.format(name=name, value=v))
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise error(f"{name} must be {'>' if lo_open else '>='} {lo:g}{u}{wording.got} {v:g}")
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise error(f"{name} must be {'<' if hi_open else '<='} {hi:g}{u}{wording.got} {v:g}")
    return v


def integer(
    value, name: str, lo: int | None = None, hi: int | None = None, error: type = InputError
) -> int:
    """`value` as an int within [lo, hi]; bools and non-integral numbers refused."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise error(f"{name} must be an integer, got {type(value).__name__} {_short(value)}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise error(
            f"{name} must be an integer in [{lo if lo is not None else '-inf'}, "
            f"{hi if hi is not None else 'inf'}], got {v}"
        )
    return v


def rigid_transform(
    T, name: str, tol: float = RIGID_TOL, max_abs_m: float = MAX_ABS_COORD_M
) -> np.ndarray:
    """`T` as a float64 4x4 if it is a rigid transform (module docstring), else InputError
    saying what is wrong with it."""
    raw = np.asarray(T)
    if raw.dtype.kind not in "fiu":
        raise InputError(f"{name} must be a 4x4 transform of numbers, got dtype {raw.dtype}")
    a = raw.astype(float)
    if a.shape != (4, 4):
        raise InputError(f"{name} must be a 4x4 transform, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} is not finite")
    if np.max(np.abs(a[3] - (0.0, 0.0, 0.0, 1.0))) > 1e-9:
        raise InputError(f"{name}: last row must be 0 0 0 1, got {_fmt(a[3])}")
    R = a[:3, :3]
    ortho = float(np.max(np.abs(R.T @ R - np.eye(3))))
    det = float(np.linalg.det(R))
    if ortho > tol or abs(det - 1.0) > tol:
        what = "a reflection" if det < 0 else ("singular" if abs(det) < tol else "not a rotation")
        raise InputError(
            f"{name}: the rotation block is {what} (max |R^T R - I| = {ortho:.3g}, det = "
            f"{det:.6g}; a rigid transform needs both within {tol:g} of a rotation)"
        )
    if float(np.max(np.abs(a[:3, 3]))) > max_abs_m:
        raise InputError(f"{name}: translation {_fmt(a[:3, 3])} m beyond +-{max_abs_m:g} m")
    return a


def imu_sample(imu, name: str = "imu") -> np.ndarray:
    """`imu` as a float64 (6,) ``[ax, ay, az, wx, wy, wz]`` within MAX_ACCEL_MPS2 /
    MAX_GYRO_RADPS."""
    if imu is None or isinstance(imu, (str, bytes, dict)):
        raise InputError(
            f"{name} must be 6 numbers [ax, ay, az, wx, wy, wz] (m/s^2, rad/s), got "
            f"{type(imu).__name__}"
        )
    try:
        raw = np.asarray(imu)
    except (TypeError, ValueError):
        raise InputError(
            f"{name} must be 6 numbers [ax, ay, az, wx, wy, wz], got {_short(imu)}"
        ) from None
    if raw.dtype.kind not in "fiu":
        raise InputError(
            f"{name} must be 6 numbers [ax, ay, az, wx, wy, wz], got dtype {raw.dtype}"
        )
    a = raw.astype(float).reshape(-1)
    if a.shape != (6,):
        raise InputError(
            f"{name} must be 6 numbers [ax, ay, az, wx, wy, wz] (m/s^2, rad/s), got {a.size}"
        )
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} is not finite ({_fmt(a)})")
    if np.max(np.abs(a[:3])) > MAX_ACCEL_MPS2 or np.max(np.abs(a[3:])) > MAX_GYRO_RADPS:
        raise InputError(
            f"{name} {_fmt(a)} is beyond physical bounds (|accel| <= {MAX_ACCEL_MPS2:g} m/s^2, "
            f"|rate| <= {MAX_GYRO_RADPS:g} rad/s)"
        )
    return a


def instance(value, name: str, cls: type, hint: str = ""):
    """`value` if an instance of `cls`, else ConfigError naming the argument and the type."""
    if not isinstance(value, cls):
        raise ConfigError(
            f"{name} must be a {cls.__name__}{f' ({hint})' if hint else ''}, got "
            f"{type(value).__name__} {_short(value)}"
        )
    return value


def gray_image(img, name: str, shape: tuple[int, int]) -> np.ndarray:
    """A grayscale image: a uint8 ndarray (as the LAC gives it; a list of lists of such values
    is converted) of `shape`."""
    if not isinstance(img, np.ndarray):
        if not isinstance(img, (list, tuple)):
            raise InputError(
                f"{name} must be a ({shape[0]}, {shape[1]}) uint8 array, got {type(img).__name__}"
            )
        try:
            img = np.asarray(img)
        except (TypeError, ValueError):
            raise InputError(
                f"{name} must be a ({shape[0]}, {shape[1]}) uint8 array, got a ragged list"
            ) from None
        if img.dtype.kind in "iu" and img.size and (img.min() < 0 or img.max() > 255):
            raise InputError(f"{name}: values must be in [0, 255], got {img.min()} .. {img.max()}")
        img = img.astype(np.uint8) if img.dtype.kind in "iu" else img
    if img.shape != tuple(shape):
        raise InputError(
            f"{name}: image shape {img.shape}, expected ({shape[0]}, {shape[1]}) grayscale "
            "(the rig's size; see CameraRig)"
        )
    if img.dtype != np.uint8:
        raise InputError(f"{name} must be a uint8 grayscale image, got dtype {img.dtype}")
    return img
