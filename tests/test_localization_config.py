"""LocalizationConfig in sections: ranges checked once, the older flat keys still load (from a
run configuration saved before the sections) and still read, and the run config round-trips."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from lunarloc.config.run import RunConfig, load_config_file
from lunarloc.core.configs import config_from_dict, config_to_dict
from lunarloc.core.errors import ConfigError
from lunarloc.localization.config import (
    MOVED_KEYS,
    DistortionConfig,
    LocalizationConfig,
    SearchConfig,
)

OLD = Path(__file__).parent / "data" / "run_config_flat_localization.json"


def test_an_old_flat_run_config_loads_into_the_sections(tmp_path):
    cfg, _ = load_config_file(OLD)
    loc = cfg.localization
    assert loc.search.epsilon_m == 0.07 and loc.search.threads == 3
    assert loc.screen.candidates == 5 and loc.refinement.enabled is False
    assert loc.distortion.scale_error == 0.01 and loc.distortion.heading_drift_deg_per_m is None
    assert loc.distortion.prior_drift_deg_per_m is None  # the loop's bend fit, as saved
    assert loc.uncertainty.sigma_floor_m == 0.004 and loc.acceptance.min_near_misses == 4
    # every setting as the file gives it, read through its old name
    old = json.loads(OLD.read_text())["localization"]
    for k, v in old.items():
        assert config_to_dict(getattr(loc, k)) == v, k
    # written back with the sections, it reads back equal
    p = tmp_path / "config.json"
    p.write_text(json.dumps(cfg.to_dict()))
    assert "search" in json.loads(p.read_text())["localization"]
    assert load_config_file(p)[0] == cfg and RunConfig.from_dict(cfg.to_dict()) == cfg


def test_every_flat_key_moves_to_one_setting():
    assert len(set(MOVED_KEYS.values())) == len(MOVED_KEYS)
    default = LocalizationConfig()
    for old, (section, new) in MOVED_KEYS.items():
        assert getattr(default, old) == getattr(getattr(default, section), new), old


def test_flat_keywords_and_replace_still_work():
    a = LocalizationConfig(epsilon_m=0.08, odometry_scale_error=0.0)
    assert a.search.epsilon_m == 0.08 and a.distortion == DistortionConfig(scale_error=0.0)
    b = replace(a, refine_radius_m=0.2)
    assert b.refinement.radius_m == 0.2 and a.refinement.radius_m == 0.1  # sections not shared
    assert a.odometry_bounds_stated and not LocalizationConfig().odometry_bounds_stated


def test_ranges_are_checked_once_when_built_or_loaded():
    with pytest.raises(ConfigError, match="radius_m"):
        LocalizationConfig(refine_radius_m=0.0)
    with pytest.raises(ConfigError, match="candidates"):
        replace(LocalizationConfig().screen, candidates=0)
    with pytest.raises(ConfigError, match="competitor_ratio=0.5 must be >= 1"):
        LocalizationConfig(competitor_ratio=0.5)
    with pytest.raises(ConfigError, match="threads=1.5 must be an integer"):
        SearchConfig(threads=1.5)
    with pytest.raises(ConfigError, match="localization.search: epsilon_m=-1.0 must be > 0"):
        RunConfig.from_dict({"localization": {"search": {"epsilon_m": -1.0}}})
    with pytest.raises(ConfigError, match="given twice"):
        config_from_dict(LocalizationConfig, {"epsilon_m": 0.1, "search": {"epsilon_m": 0.2}})
    with pytest.raises(ConfigError, match="yaw-only"):
        LocalizationConfig(mode="6dof", registration="yaw")


def test_cli_style_options_reach_the_sections():
    cfg = RunConfig().with_options(
        localization__search__epsilon_m=0.07,
        localization__distortion__scale_error=0.01,
        localization__mode="6dof",
    )
    loc = cfg.localization
    assert loc.search.epsilon_m == 0.07 and loc.distortion.scale_error == 0.01
    assert (
        loc.mode.value == "6dof"
        and loc.search.epsilon_z_m == RunConfig().localization.search.epsilon_z_m
    )
    with pytest.raises(ConfigError, match="localization.search.epsilon_m"):
        RunConfig().with_options(localization__search__epsilon_m=5.0)  # over the run config's cap
    # the older flat names of a caller's options still reach their settings
    old = RunConfig().with_options(localization__epsilon_m=0.07, localization__screen_candidates=4)
    assert old.localization.search.epsilon_m == 0.07 and old.localization.screen.candidates == 4
