"""One run configuration that round-trips: :class:`RunConfig`.

Every command that runs a pipeline (``run``, ``detect``, ``localize``, ``bench loop``, ``demo``)
writes its full configuration (``config.json`` in run folders, next to other outputs) and reads
one back with ``--config FILE``; command-line options then override single settings. Sections:

- ``detector``: :class:`~lunarloc.perception.detector.DetectorConfig`, tuned at
  ``detector_tuned_width_px`` and scaled to the images' width by :func:`scaled_detector_config`;
- ``localization``: :class:`~lunarloc.localization.config.LocalizationConfig`;
- ``index``: :class:`~lunarloc.association.index.IndexConfig` (the rock-triangle index of
  large references, used by ``localize``'s indexed search);
- ``loop``: :class:`~lunarloc.online.loop.LoopConfig` (local map, attempts, fusion);
- ``odometry``: :class:`OdometryConfig` (where the odometry comes from, IMU and visual
  odometry settings, and the simulated drift of traverse-CSV runs).

A file may hold other sections that a command reads itself (``scenario`` for ``demo``) and an
``info`` section (what a run used: source, camera, odometry), written for the record and
ignored when read. Any other key, or a value of the wrong type or out of range, is a
:class:`~lunarloc.core.errors.ConfigError` naming the key (``loop.window_m: ...``).

:func:`config_to_dict` / :func:`config_from_dict` do the conversion for any config dataclass
(nested dataclasses, Enums, tuples, optional values).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any


from lunarloc.association.index import IndexConfig
from lunarloc.core.configs import config_from_dict, config_to_dict
from lunarloc.core.errors import ConfigError
from lunarloc.localization.config import LocalizationConfig
from lunarloc.online.loop import (
    LoopConfig,
    image_localization_config,
    image_loop_config,
    loop_localization_config,
)
from lunarloc.odometry.imu import ImuOdometryConfig
from lunarloc.perception.detector import scaled_detector_config

__all__ = [
    "RunConfig",
    "OdometryConfig",
    "config_to_dict",
    "config_from_dict",
    "scaled_detector_config",
    "load_config_file",
    "check_limits",
    "SETTING_LIMITS",
]

INFO_SECTION = "info"
MAX_CONFIG_BYTES = 4 * 1024**2  # a run configuration is a few kB


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number a setting can take (JSON has no NaN or Infinity)")


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class OdometryConfig:
    """Where a run's odometry comes from and how it is computed."""

    # visual | imu | record:NAME | ground-truth (evaluation only); None: visual when the
    # archive has front stereo pairs, else imu (lunarloc.odometry.source.OdometrySource)
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
            object.__setattr__(
                self, "visual", config_from_dict(VisualOdometryConfig, self.visual, "visual")
            )
        elif not isinstance(self.visual, VisualOdometryConfig):
            raise ConfigError(
                f"visual: expected VisualOdometryConfig settings, got {type(self.visual).__name__}"
            )
        if self.source is not None:
            from lunarloc.odometry.source import parse_odometry_source

            parse_odometry_source(self.source)  # ConfigError naming the valid sources
        if not (
            0 <= self.heading_drift_deg_per_m <= 10
            and -0.5 <= self.scale_error <= 0.5
            and 0 < self.rate_hz <= 1000
        ):
            raise ConfigError(
                f"heading_drift_deg_per_m={self.heading_drift_deg_per_m} (0..10), scale_error="
                f"{self.scale_error} (-0.5..0.5), rate_hz={self.rate_hz} (0..1000]"
            )

    @property
    def drift(self):
        """The simulated drift of traverse-CSV runs
        (:class:`lunarloc.odometry.drift.DriftModel`)."""
        from lunarloc.odometry.drift import DriftModel

        return DriftModel(self.heading_drift_deg_per_m, self.scale_error)


def _detector_default():
    from lunarloc.perception.detector import DetectorConfig

    return DetectorConfig()


@dataclass(frozen=True)
class RunConfig:
    """The full configuration of a run (see the module docstring). The defaults are those of
    runs on images (``lunarloc run``, ``demo``); :meth:`for_detections` gives those of runs on
    the real dataset's detections (``bench loop``)."""

    # DetectorConfig, at detector_tuned_width_px
    detector: Any = field(default_factory=_detector_default)
    detector_tuned_width_px: int = 1280  # the detector's pixel sizes are tuned at this image width
    localization: LocalizationConfig = field(default_factory=image_localization_config)
    index: IndexConfig = field(default_factory=IndexConfig)
    loop: LoopConfig = field(default_factory=image_loop_config)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)

    def __post_init__(self) -> None:
        from lunarloc.perception.detector import DetectorConfig

        if isinstance(self.detector, Mapping):
            object.__setattr__(
                self, "detector", config_from_dict(DetectorConfig, self.detector, "detector")
            )
        elif not isinstance(self.detector, DetectorConfig):
            raise ConfigError(
                f"detector: expected DetectorConfig settings, got {type(self.detector).__name__}"
            )
        if (
            not isinstance(self.detector_tuned_width_px, int)
            or not 64 <= self.detector_tuned_width_px <= 8192
        ):
            raise ConfigError(
                f"detector_tuned_width_px={self.detector_tuned_width_px!r} must be an integer in "
                "[64, 8192]"
            )

    @classmethod
    def for_detections(cls, **overrides) -> RunConfig:
        """Runs on the LunarLoc dataset's detections (no images): the default localization
        and a 12 m local map. Its windows state the simulated drift until the pose graph has
        calibrated it (2 fixes), then their bend is fitted (docs/online-component.md). Its
        fixes are stated with the window distortion counted as a 3-sigma bound and a 6 mm
        (0.5 mm vertical) centre bias the window's rocks share, their headings with the
        turn the pose graph's heading bias carried into its prediction since its last solve as
        one sigma (docs/calibration.md, "The online loop's uncertainty")."""
        return cls(
            **{
                "localization": loop_localization_config(),
                "loop": LoopConfig(
                    calibrated_after_fixes=2,
                    fix_distortion_sigmas=3.0,
                    fix_centre_bias_m=0.006,
                    fix_centre_bias_z_m=0.0005,
                    fix_heading_turn_factor=1.0,
                ),
                **overrides,
            }
        )

    def detector_for(self, width: int):
        """The detector's config for images `width` pixels wide."""
        return scaled_detector_config(width, self.detector, self.detector_tuned_width_px)

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping, extra_sections: tuple[str, ...] = ()) -> RunConfig:
        """From :meth:`to_dict`'s output; the ``info`` section and `extra_sections` are skipped."""
        if not isinstance(data, Mapping):
            raise ConfigError(
                f"a run configuration is a table of sections, got {type(data).__name__}"
            )
        return config_from_dict(
            cls, {k: v for k, v in data.items() if k not in (INFO_SECTION, *extra_sections)}
        )

    def with_options(self, **settings) -> RunConfig:
        """A copy with settings given as ``section__name=value`` or
        ``section__subsection__name=value`` (None: keep), e.g. ``loop__window_m=8.0``,
        ``localization__search__epsilon_m=0.08``: how command-line options override a config
        file. The settings of one section are applied together (checked once)."""
        by_section: dict[str, dict] = {}
        for key, value in settings.items():
            if value is not None:
                section, *path = key.split("__")
                values = by_section.setdefault(section, {})
                for sub in path[:-1]:
                    values = values.setdefault(sub, {})
                values[path[-1]] = value
        out = self
        for section, values in by_section.items():
            try:
                out = replace(out, **{section: _replaced(getattr(out, section), values)})
            except ConfigError as exc:
                raise ConfigError(f"{section}: {exc}") from None
        return check_limits(out) if by_section else out


def _replaced(cfg, values: Mapping):
    """`cfg` with `values` set, a nested table replacing settings of that subsection."""
    return replace(
        cfg,
        **{
            k: _replaced(getattr(cfg, k), v) if isinstance(v, Mapping) else v
            for k, v in values.items()
        },
    )


#: Caps on settings, the same whether a value comes from a command-line option or from a
#: ``--config`` file (``localization.search.epsilon_m = 10`` in a file bypassed the CLI's
#: 0.3 m cap and ran for minutes): (low, high, unit); a low end of 0.0 is exclusive (a length,
#: a rate), any other low end inclusive. Beyond these, every number in a configuration must
#: lie within +-MAX_SETTING_MAGNITUDE.
SETTING_LIMITS: dict[str, tuple[float, float, str]] = {
    # the consistency graph grows with it (docs/robustness.md)
    "localization.search.epsilon_m": (0.0, 0.3, "m"),
    "localization.search.epsilon_z_m": (0.0, 0.3, "m"),
    "localization.search.sigma_m": (0.0, 0.3, "m"),
    "localization.refinement.radius_m": (0.0, 10.0, "m"),
    "localization.acceptance.near_miss_outer_m": (0.0, 10.0, "m"),
    "localization.search.yaw_step_deg": (0.1, 45.0, "deg"),
    "localization.acceptance.max_predicted_error_m": (0.0, 100.0, "m"),
    "localization.acceptance.max_rmse_m": (0.0, 10.0, "m"),
    "localization.search.threads": (1, 256, ""),
    "localization.search.max_edges": (1, 1_000_000_000, ""),
    "localization.acceptance.min_inliers": (3, 1_000_000, ""),
    "localization.screen.candidates": (1, 10_000, ""),
    "loop.localize_every_m": (0.0, 1e6, "m"),
    "loop.localize_every_s": (0.0, 1e7, "s"),
    "loop.window_m": (0.0, 1e6, "m"),
    "loop.crop_margin_m": (-1.0, 1e6, "m"),  # the low end: LoopConfig's own check (>= 0)
    "loop.keyframe_every_s": (1e-3, 1e7, "s"),
    "loop.keyframe_max_interval_s": (1e-3, 1e7, "s"),
    "loop.min_window_landmarks": (3, 1_000_000, ""),
    # the low end: OdometryConfig's (>= 0)
    "odometry.heading_drift_deg_per_m": (-1.0, 10.0, "deg/m"),
    "odometry.scale_error": (-0.5, 0.5, ""),
    "odometry.rate_hz": (0.0, 1000.0, "Hz"),
}
MAX_SETTING_MAGNITUDE = 1e9


def _numbers(d, prefix: str = ""):
    if isinstance(d, Mapping):
        for k, v in d.items():
            yield from _numbers(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(d, (list, tuple)):
        for i, v in enumerate(d):
            yield from _numbers(v, f"{prefix}[{i}]")
    elif isinstance(d, (int, float)) and not isinstance(d, bool):
        yield prefix, d


def check_limits(cfg: RunConfig) -> RunConfig:
    """`cfg` if every setting is within :data:`SETTING_LIMITS` and every number within
    +-:data:`MAX_SETTING_MAGNITUDE`; else a ConfigError naming the first one that is not."""
    values = dict(_numbers(cfg.to_dict()))
    for key, (lo, hi, unit) in SETTING_LIMITS.items():
        v = values.get(key)
        if v is None:
            continue
        if not ((v > lo if lo == 0.0 else v >= lo) and v <= hi):
            rng = f"({lo:g}, {hi:g}]" if lo == 0.0 else f"[{lo:g}, {hi:g}]"
            raise ConfigError(f"{key}: {v!r} outside {rng}{' ' + unit if unit else ''}")
    for key, v in values.items():
        if abs(v) > MAX_SETTING_MAGNITUDE:
            raise ConfigError(
                f"{key}: {v!r} beyond +-{MAX_SETTING_MAGNITUDE:g}, not a plausible setting"
            )
    return cfg


def load_config_file(
    path: str | Path, extra_sections: tuple[str, ...] = ()
) -> tuple[RunConfig, dict]:
    """A :class:`RunConfig` from a JSON file (a run folder's ``config.json`` or one written by
    ``--config``'s commands), and the `extra_sections` it holds. Errors name the file."""
    from lunarloc.io.inputs import check_input_file

    path = check_input_file(path, MAX_CONFIG_BYTES, "run configuration")
    try:
        data = json.loads(path.read_text(encoding="utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not a JSON run configuration ({exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not a JSON run configuration (nested too deeply)") from None
    except ValueError as exc:  # NaN / Infinity literals, integers of thousands of digits
        raise ConfigError(f"{path}: {exc}") from None
    try:
        cfg = check_limits(RunConfig.from_dict(data, extra_sections))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: a setting is nested too deeply") from None
    return cfg, {k: data[k] for k in extra_sections if k in data}
