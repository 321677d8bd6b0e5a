"""Config dataclasses as plain values and back: :func:`config_to_dict` / :func:`config_from_dict`
(nested dataclasses, Enums, tuples, optional values), with a ConfigError naming the key for a
value of the wrong type or one the config refuses."""

from __future__ import annotations

import enum
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING, fields, is_dataclass, replace
from typing import Any

import numpy as np

from lunarloc.core.errors import ConfigError

__all__ = ["config_to_dict", "config_from_dict"]


def config_to_dict(obj) -> Any:
    """A config dataclass as plain JSON values (nested dataclasses as dicts, Enums as their
    values, tuples as lists)."""
    if is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: config_to_dict(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, enum.Enum):
        return obj.value
    if isinstance(obj, (list, tuple)):
        return [config_to_dict(v) for v in obj]
    if isinstance(obj, Mapping):
        return {str(k): config_to_dict(v) for k, v in obj.items()}
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def config_from_dict(cls, data, where: str = "", base=None):
    """The config dataclass `cls` from plain values (as :func:`config_to_dict` writes them).
    Missing keys keep their defaults (those of `base`, an instance of `cls`, when given); a
    nested section given in part keeps the rest of its field's own default (e.g. the height
    map's SGBM settings, not StereoConfig's); an unknown key, a value of the wrong type or
    one the config refuses is a ConfigError naming the key (``where`` is the section path)."""
    label = where or cls.__name__
    if not isinstance(data, Mapping):
        raise ConfigError(f"{label}: expected a table of settings, got {type(data).__name__} {data!r:.60}")
    hints = typing.get_type_hints(cls)
    known = [f.name for f in fields(cls) if f.init]
    unknown = [k for k in data if k not in known]
    if unknown:
        key = f"{where}.{unknown[0]}" if where else str(unknown[0])
        raise ConfigError(f"unknown setting {key!r} (known in {label}: {', '.join(known)})")
    kwargs = {k: _convert(hints[k], v, f"{where}.{k}" if where else k,
                          getattr(base, k) if base is not None else _field_default(cls, k)) for k, v in data.items()}
    try:
        return replace(base, **kwargs) if base is not None else cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{label}: {exc}" if where else str(exc)) from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{label}: {exc}") from None


def _field_default(cls, name: str):
    """The default value of dataclass `cls`'s field `name` (None when it has none)."""
    f = next(f for f in fields(cls) if f.name == name)
    if f.default_factory is not MISSING:
        return f.default_factory()
    return None if f.default is MISSING else f.default


def _convert(tp, v, key: str, default=None):
    """`v` as a value of the annotated type `tp`; a ConfigError naming `key` when it is not one
    (`default`: the field's current value, the base of a nested section given in part)."""
    return _converter(tp)(tp, v, key, default)


def _converter(tp):
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return _to_union
    if origin is tuple:
        return _to_tuple
    if is_dataclass(tp):
        return _to_section
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return _to_enum
    return _SCALARS.get(tp, lambda tp, v, key, default: v)


def _to_union(tp, v, key, default):
    args = typing.get_args(tp)
    if v is None and type(None) in args:
        return None
    errors = []
    for a in (a for a in args if a is not type(None)):
        try:
            return _convert(a, v, key, default)
        except ConfigError as exc:
            errors.append(str(exc))
    raise ConfigError(errors[0] if len(errors) == 1 else f"{key}: {v!r} fits none of {tp}")


def _to_section(tp, v, key, default):
    return config_from_dict(tp, v, key, default if isinstance(default, tp) else None)


def _to_enum(tp, v, key, default):
    try:
        return tp(v)
    except ValueError:
        raise ConfigError(f"{key}: {v!r} is not one of {', '.join(str(m.value) for m in tp)}") from None


def _to_tuple(tp, v, key, default):
    args = typing.get_args(tp)
    if not isinstance(v, (list, tuple)):
        raise ConfigError(f"{key}: expected a list, got {v!r}")
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_convert(args[0], x, f"{key}[{i}]") for i, x in enumerate(v))
    if args and len(args) != len(v):
        raise ConfigError(f"{key}: expected {len(args)} values, got {len(v)}")
    return tuple(_convert(a, x, f"{key}[{i}]") for i, (a, x) in enumerate(zip(args, v))) if args else tuple(v)


def _to_bool(tp, v, key, default):
    if not isinstance(v, bool):
        raise ConfigError(f"{key}: expected true or false, got {v!r}")
    return v


def _to_int(tp, v, key, default):
    if isinstance(v, bool) or not (isinstance(v, int) or (isinstance(v, float) and v.is_integer())):
        raise ConfigError(f"{key}: expected an integer, got {v!r}")
    return int(v)


def _to_float(tp, v, key, default):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{key}: expected a finite number, got {v!r}")
    return float(v)


def _to_str(tp, v, key, default):
    if not isinstance(v, str):
        raise ConfigError(f"{key}: expected a string, got {v!r}")
    return v


_SCALARS = {bool: _to_bool, int: _to_int, float: _to_float, str: _to_str}
