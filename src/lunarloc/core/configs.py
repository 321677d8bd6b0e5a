"""Config dataclasses as plain values and back: :func:`config_to_dict` / :func:`config_from_dict`
(nested dataclasses, Enums, tuples, optional values), with a ConfigError naming the key for a
value of the wrong type or one the config refuses.

Declarative ranges: a field declared with :func:`setting` states its range beside it
(``tol_m: float = setting(0.2, ge=0.0)``); :func:`check_settings`, called once from the
config's ``__post_init__``, checks every such field's type (from its annotation) and range.
Moved keys: :func:`moved_keys` lets a config that grew sections still take the flat keys of
older files and code (``DetectorConfig(fuse_tol_m=0.2)``, ``{"fuse_tol_m": 0.2}`` in a saved
``config.json``), each moved into its section."""

from __future__ import annotations

import enum
import functools
import math
import numbers
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from typing import Any

import numpy as np

from lunarloc.core.errors import ConfigError

__all__ = ["Range", "check_settings", "config_from_dict", "config_to_dict", "moved_keys", "setting"]


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
        raise ConfigError(
            f"{label}: expected a table of settings, got {type(data).__name__} {data!r:.60}"
        )
    old = [k for k in data if k in getattr(cls, "MOVED_KEYS", {})]
    if old:
        try:
            return config_from_dict(cls, nest_moved_keys(cls, data, tables=True), where, base)
        except ConfigError as exc:
            raise ConfigError(f"{exc} (older flat keys given: {', '.join(old)})") from None
    hints = typing.get_type_hints(cls)
    known = [f.name for f in fields(cls) if f.init]
    unknown = [k for k in data if k not in known]
    if unknown:
        key = f"{where}.{unknown[0]}" if where else str(unknown[0])
        raise ConfigError(f"unknown setting {key!r} (known in {label}: {', '.join(known)})")
    kwargs = {
        k: _convert(
            hints[k],
            v,
            f"{where}.{k}" if where else k,
            getattr(base, k) if base is not None else _field_default(cls, k),
        )
        for k, v in data.items()
    }
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
        raise ConfigError(
            f"{key}: {v!r} is not one of {', '.join(str(m.value) for m in tp)}"
        ) from None


def _to_tuple(tp, v, key, default):
    args = typing.get_args(tp)
    if not isinstance(v, (list, tuple)):
        raise ConfigError(f"{key}: expected a list, got {v!r}")
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_convert(args[0], x, f"{key}[{i}]") for i, x in enumerate(v))
    if args and len(args) != len(v):
        raise ConfigError(f"{key}: expected {len(args)} values, got {len(v)}")
    return (
        tuple(_convert(a, x, f"{key}[{i}]") for i, (a, x) in enumerate(zip(args, v)))
        if args
        else tuple(v)
    )


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


# ---------------------------------------------------------------------- declarative ranges
@dataclass(frozen=True)
class Range:
    """The values a numeric setting accepts: bounds (``ge``/``gt`` low, ``le``/``lt`` high),
    or a set of ``choices``, and optionally ``multiple_of``."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple | None = None
    multiple_of: int | None = None

    def contains(self, v) -> bool:
        if self.choices is not None:
            return v in self.choices
        return (
            (self.ge is None or v >= self.ge)
            and (self.gt is None or v > self.gt)
            and (self.le is None or v <= self.le)
            and (self.lt is None or v < self.lt)
            and (self.multiple_of is None or v % self.multiple_of == 0)
        )

    def describe(self) -> str:
        """The range as text: ``[0, 1]``, ``(0, 0.5]``, ``>= 0``, ``one of 1, 2``."""
        if self.choices is not None:
            return "one of " + ", ".join(str(c) for c in self.choices)
        lo = self.ge if self.ge is not None else self.gt
        hi = self.le if self.le is not None else self.lt
        mult = f", a multiple of {self.multiple_of}" if self.multiple_of else ""
        if lo is not None and hi is not None:
            left = "[" if self.ge is not None else "("
            right = "]" if self.le is not None else ")"
            return f"{left}{lo:g}, {hi:g}{right}{mult}"
        if lo is not None:
            return f"{'>=' if self.ge is not None else '>'} {lo:g}{mult}"
        if hi is not None:
            return f"{'<=' if self.le is not None else '<'} {hi:g}{mult}"
        return f"any{mult}"


def setting(
    default=MISSING,
    *,
    default_factory=MISSING,
    ge=None,
    gt=None,
    le=None,
    lt=None,
    choices=None,
    multiple_of=None,
):
    """A dataclass field whose range is stated where it is declared (see :class:`Range`);
    :func:`check_settings` checks it."""
    rng = Range(ge, gt, le, lt, None if choices is None else tuple(choices), multiple_of)
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata={"range": rng})
    return field(default=default, metadata={"range": rng})


@functools.cache
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _type_ok(tp, v) -> bool:
    if tp is bool:
        return isinstance(v, (bool, np.bool_))
    if tp is int:
        return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))
    if tp is float:
        return (
            isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)
        )
    return True


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a finite number"}


def check_settings(obj) -> None:
    """Check every field of the config dataclass `obj` declared with :func:`setting`: its type
    (bool, int or float, by its annotation) and its range. ConfigError naming the field."""
    hints = _hints(type(obj))
    for f in fields(obj):
        rng = f.metadata.get("range")
        if rng is None:
            continue
        v, tp = getattr(obj, f.name), hints[f.name]
        # an optional setting: None passes
        if typing.get_origin(tp) in (typing.Union, types.UnionType):
            if v is None and type(None) in typing.get_args(tp):
                continue
            tp = next((a for a in typing.get_args(tp) if a is not type(None)), tp)
        if not _type_ok(tp, v):
            raise ConfigError(f"{f.name}={v!r} must be {_TYPE_WORDS.get(tp, tp)}, {rng.describe()}")
        if not rng.contains(v):
            raise ConfigError(f"{f.name}={v!r} must be {rng.describe()}")


# ---------------------------------------------------------------------- moved keys
def nest_moved_keys(cls, data: Mapping, tables: bool = False) -> dict:
    """`data` (keyword arguments or, with `tables`, a table of settings for `cls`) with the older
    flat keys of ``cls.MOVED_KEYS`` ({old: (section, new)}) moved into their sections: into the
    section's table when `data` gives one (or `tables` and it gives none), else into a copy of
    the section's config (given or default). ConfigError when a key is given both ways."""
    moved = cls.MOVED_KEYS
    out = {k: v for k, v in data.items() if k not in moved}
    by_section: dict[str, dict] = {}
    for k, v in data.items():
        if k in moved:
            section, new = moved[k]
            by_section.setdefault(section, {})[new] = (k, v)
    for section, values in by_section.items():
        base = out.get(section, {} if tables else MISSING)
        if isinstance(base, Mapping):
            twice = [old for new, (old, _) in values.items() if new in base]
            if twice:
                raise ConfigError(
                    f"{twice[0]!r} given twice: flat and as {section}.{moved[twice[0]][1]}"
                )
            out[section] = {**base, **{new: v for new, (_, v) in values.items()}}
            continue
        if base is MISSING:
            base = _field_default(cls, section)
        try:
            out[section] = replace(base, **{new: v for new, (_, v) in values.items()})
        except (TypeError, ConfigError) as exc:
            olds = ", ".join(old for old, _ in values.values())
            raise ConfigError(f"{section}: {exc} (older flat keys given: {olds})") from None
    return out


def moved_keys(mapping: Mapping[str, tuple[str, str]]):
    """Class decorator for a config dataclass whose flat settings moved into sections:
    ``mapping`` is {old flat key: (section field, new key)}. The class then also takes the old
    keys as keyword arguments (so ``dataclasses.replace`` takes them too), reads them as
    attributes, and :func:`config_from_dict` takes them in a table (files saved before the move)."""

    def wrap(cls):
        cls.MOVED_KEYS = dict(mapping)
        init = cls.__init__

        @functools.wraps(init)
        def __init__(self, *args, **kwargs):
            old = [k for k in kwargs if k in cls.MOVED_KEYS]
            if not old:
                return init(self, *args, **kwargs)
            nested = nest_moved_keys(cls, kwargs)
            try:
                init(self, *args, **nested)
            except ConfigError as exc:
                raise ConfigError(f"{exc} (older flat keys given: {', '.join(old)})") from None

        def __getattr__(self, name):
            where = cls.MOVED_KEYS.get(name)
            if where is None:
                raise AttributeError(f"{cls.__name__!r} object has no attribute {name!r}")
            return getattr(object.__getattribute__(self, where[0]), where[1])

        cls.__init__ = __init__
        cls.__getattr__ = __getattr__
        return cls

    return wrap
