"""The loop's presets as data: JSON files beside this module, one per preset, each a partial
table of its config's settings (sections as nested tables; ``null`` for a setting that is None),
read by :func:`load_preset`. What each was measured with: docs/online-component.md.

* ``loop_localization.json``: the localization of the loop's windows on the real dataset's
  detections (the bend fit without the one-shot's odometry prior);
* ``image_localization.json``: the same for detections from simulated stereo images (wider
  tolerances);
* ``image_loop.json``: the loop for detections from stereo images (8 m window growing to 12 m,
  the crop sized by the window's odometry bounds).
"""

from __future__ import annotations

import functools
import json
from dataclasses import replace
from importlib import resources

from lunarloc.core.configs import config_from_dict
from lunarloc.core.errors import ConfigError

__all__ = ["PRESETS", "preset_table", "load_preset"]

PRESETS = ("loop_localization", "image_localization", "image_loop")


@functools.cache
def _read(name: str) -> str:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r} (presets: {', '.join(PRESETS)})")
    return resources.files(__name__).joinpath(f"{name}.json").read_text(encoding="utf-8")


def preset_table(name: str) -> dict:
    """The preset `name`'s settings as plain values (a fresh copy)."""
    return json.loads(_read(name))


def load_preset(cls, name: str, **overrides):
    """The config dataclass `cls` with the preset `name`'s settings over its defaults, then
    `overrides` (keyword arguments as ``cls`` takes them; older flat keys too)."""
    cfg = config_from_dict(cls, preset_table(name), where=f"preset {name}")
    return replace(cfg, **overrides) if overrides else cfg
