"""One run configuration that round-trips: :class:`RunConfig`.

Every command that runs a pipeline (``run``, ``detect``, ``localize``, ``bench loop``, ``demo``)
writes its full configuration (``config.json`` in run folders, next to other outputs) and reads
one back with ``--config FILE``; command-line options then override single settings. Sections:

- ``detector``: :class:`~lunarloc.perception.detector.DetectorConfig`, tuned at
  ``detector_tuned_width_px`` and scaled to the images' width by :func:`scaled_detector_config`;
- ``localization``: :class:`~lunarloc.localize.LocalizationConfig`;
- ``index``: :class:`~lunarloc.association.index.IndexConfig` (the rock-triangle index of
  large references, used by ``localize``'s indexed search);
- ``loop``: :class:`~lunarloc.loop.LoopConfig` (local map, attempts, fusion);
- ``odometry``: :class:`OdometryConfig` (where the odometry comes from, IMU and visual
  odometry settings, and the simulated drift of traverse-CSV runs).

A file may hold other sections that a command reads itself (``scenario`` for ``demo``) and an
``info`` section (what a run used: source, camera, odometry), written for the record and
ignored when read. Any other key, or a value of the wrong type or out of range, is a
:class:`~lunarloc.errors.ConfigError` naming the key (``loop.window_m: ...``).

:func:`config_to_dict` / :func:`config_from_dict` do the conversion for any config dataclass
(nested dataclasses, Enums, tuples, optional values).
"""

from __future__ import annotations

import enum
import json
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from lunarloc.association.index import IndexConfig
from lunarloc.errors import ConfigError
from lunarloc.localize import LocalizationConfig
from lunarloc.loop import LoopConfig, image_localization_config, image_loop_config, loop_localization_config
from lunarloc.odometry.imu import ImuOdometryConfig

__all__ = ["RunConfig", "OdometryConfig", "config_to_dict", "config_from_dict", "scaled_detector_config",
           "load_config_file"]  # fmt: skip

INFO_SECTION = "info"


# --------------------------------------------------------------------------- conversion


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
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
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
    if is_dataclass(tp):
        return config_from_dict(tp, v, key, default if isinstance(default, tp) else None)
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        try:
            return tp(v)
        except ValueError:
            raise ConfigError(f"{key}: {v!r} is not one of {', '.join(str(m.value) for m in tp)}") from None
    if tp is bool:
        if not isinstance(v, bool):
            raise ConfigError(f"{key}: expected true or false, got {v!r}")
        return v
    if tp is int:
        if isinstance(v, bool) or not (isinstance(v, int) or (isinstance(v, float) and v.is_integer())):
            raise ConfigError(f"{key}: expected an integer, got {v!r}")
        return int(v)
    if tp is float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(f"{key}: expected a finite number, got {v!r}")
        return float(v)
    if tp is str:
        if not isinstance(v, str):
            raise ConfigError(f"{key}: expected a string, got {v!r}")
        return v
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(v, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {v!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], x, f"{key}[{i}]") for i, x in enumerate(v))
        if args and len(args) != len(v):
            raise ConfigError(f"{key}: expected {len(args)} values, got {len(v)}")
        return tuple(_convert(a, x, f"{key}[{i}]") for i, (a, x) in enumerate(zip(args, v))) if args else tuple(v)
    return v


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class OdometryConfig:
    """Where a run's odometry comes from and how it is computed."""

    # visual | imu | record:NAME | ground-truth (evaluation only); None: visual when the
    # archive has front stereo pairs, else imu (lunarloc.odometry.OdometrySource)
    source: str | None = None
    imu: ImuOdometryConfig = field(default_factory=ImuOdometryConfig)
    visual: Any = None  # VisualOdometryConfig (None: its defaults), see __post_init__
    # traverse-CSV runs (no odometry recorded): simulated drift and frame rate
    heading_drift_deg_per_m: float = 0.05
    scale_error: float = 0.02
    rate_hz: float = 20.0

    def __post_init__(self) -> None:
        from lunarloc.odometry.visual import VisualOdometryConfig

        if self.visual is None:
            object.__setattr__(self, "visual", VisualOdometryConfig())
        elif isinstance(self.visual, Mapping):
            object.__setattr__(self, "visual", config_from_dict(VisualOdometryConfig, self.visual, "visual"))
        elif not isinstance(self.visual, VisualOdometryConfig):
            raise ConfigError(f"visual: expected VisualOdometryConfig settings, got {type(self.visual).__name__}")
        if self.source is not None:
            from lunarloc.odometry import parse_odometry_source

            parse_odometry_source(self.source)  # ConfigError naming the valid sources
        if not (0 <= self.heading_drift_deg_per_m <= 10 and -0.5 <= self.scale_error <= 0.5 and 0 < self.rate_hz <= 1000):
            raise ConfigError(f"heading_drift_deg_per_m={self.heading_drift_deg_per_m} (0..10), scale_error="
                              f"{self.scale_error} (-0.5..0.5), rate_hz={self.rate_hz} (0..1000]")  # fmt: skip

    @property
    def drift(self):
        """The simulated drift of traverse-CSV runs (:class:`lunarloc.evaluation.DriftModel`)."""
        from lunarloc.evaluation import DriftModel

        return DriftModel(self.heading_drift_deg_per_m, self.scale_error)


def _detector_default():
    from lunarloc.perception.detector import DetectorConfig

    return DetectorConfig()


@dataclass(frozen=True)
class RunConfig:
    """The full configuration of a run (see the module docstring). The defaults are those of
    runs on images (``lunarloc run``, ``demo``); :meth:`for_detections` gives those of runs on
    the real dataset's detections (``bench loop``)."""

    detector: Any = field(default_factory=_detector_default)  # DetectorConfig, at detector_tuned_width_px
    detector_tuned_width_px: int = 1280  # the detector's pixel sizes are tuned at this image width
    localization: LocalizationConfig = field(default_factory=image_localization_config)
    index: IndexConfig = field(default_factory=IndexConfig)
    loop: LoopConfig = field(default_factory=image_loop_config)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)

    def __post_init__(self) -> None:
        from lunarloc.perception.detector import DetectorConfig

        if isinstance(self.detector, Mapping):
            object.__setattr__(self, "detector", config_from_dict(DetectorConfig, self.detector, "detector"))
        elif not isinstance(self.detector, DetectorConfig):
            raise ConfigError(f"detector: expected DetectorConfig settings, got {type(self.detector).__name__}")
        if not isinstance(self.detector_tuned_width_px, int) or not 64 <= self.detector_tuned_width_px <= 8192:
            raise ConfigError(f"detector_tuned_width_px={self.detector_tuned_width_px!r} must be an integer in [64, 8192]")

    @classmethod
    def for_detections(cls, **overrides) -> RunConfig:
        """Runs on the LunarLoc dataset's detections (no images): the default localization
        and a 12 m local map. Its windows state the simulated drift until the pose graph has
        calibrated it (2 fixes), then their bend is fitted (docs/online-component.md)."""
        return cls(**{"localization": loop_localization_config(), "loop": LoopConfig(calibrated_after_fixes=2),
                      **overrides})  # fmt: skip

    def detector_for(self, width: int):
        """The detector's config for images `width` pixels wide."""
        return scaled_detector_config(width, self.detector, self.detector_tuned_width_px)

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping, extra_sections: tuple[str, ...] = ()) -> RunConfig:
        """From :meth:`to_dict`'s output; the ``info`` section and `extra_sections` are skipped."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"a run configuration is a table of sections, got {type(data).__name__}")
        return config_from_dict(cls, {k: v for k, v in data.items() if k not in (INFO_SECTION, *extra_sections)})

    def with_options(self, **settings) -> RunConfig:
        """A copy with settings given as ``section__name=value`` (None: keep), e.g.
        ``loop__window_m=8.0``: how command-line options override a config file. The
        settings of one section are applied together (checked once)."""
        by_section: dict[str, dict] = {}
        for key, value in settings.items():
            if value is not None:
                section, name = key.split("__")
                by_section.setdefault(section, {})[name] = value
        out = self
        for section, values in by_section.items():
            try:
                out = replace(out, **{section: replace(getattr(out, section), **values)})
            except ConfigError as exc:
                raise ConfigError(f"{section}: {exc}") from None
        return out


def load_config_file(path: str | Path, extra_sections: tuple[str, ...] = ()) -> tuple[RunConfig, dict]:
    """A :class:`RunConfig` from a JSON file (a run folder's ``config.json`` or one written by
    ``--config``'s commands), and the `extra_sections` it holds. Errors name the file."""
    from lunarloc.inputs import check_input_file

    path = check_input_file(path, None, "run configuration")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not a JSON run configuration ({exc})") from None
    try:
        cfg = RunConfig.from_dict(data, extra_sections)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return cfg, {k: data[k] for k in extra_sections if k in data}


def scaled_detector_config(width: int, base=None, tuned_width_px: int = 1280):
    """Detector config for images `width` pixels wide: the pixel-sized parameters of `base`
    (tuned at `tuned_width_px`) scaled to the resolution. Below the tuned width the range cap
    drops to 5 m and the SGBM block shrinks (coarser pixels, larger depth error at range)."""
    from lunarloc.perception.detector import DetectorConfig

    base = base or DetectorConfig()
    f = width / float(tuned_width_px)
    if abs(f - 1.0) < 1e-6:
        return base
    c, fl, st = base.classical, base.filters, base.stereo
    return replace(
        base,
        classical=replace(c, bg_median_px=max(16, int(c.bg_median_px * f)), min_area_px=max(4, int(c.min_area_px * f * f))),
        filters=replace(fl, min_area_px=max(4, int(fl.min_area_px * f * f)), max_range_m=min(fl.max_range_m, 5.0) if f < 1 else fl.max_range_m),
        stereo=replace(st, num_disparities=max(16, int(st.num_disparities * f) // 16 * 16), block_size=7 if f < 1 else st.block_size),
        height_filters=replace(base.height_filters, near_sigma_px=base.height_filters.near_sigma_px * f),
    )  # fmt: skip
