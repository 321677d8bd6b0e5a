"""The loop's presets are data files (src/lunarloc/online/presets/*.json) read by one function:
each loads into its config, None is expressible (``null``), overrides apply on top."""

from __future__ import annotations

import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.localization.config import LocalizationConfig
from lunarloc.online.loop import (
    IMAGE_WINDOW_M,
    CropSigma,
    LoopConfig,
    image_localization_config,
    image_loop_config,
    loop_localization_config,
)
from lunarloc.online.presets import PRESETS, load_preset, preset_table


def test_the_loop_windows_fit_their_bend_without_the_prior():
    loc = loop_localization_config()
    assert loc.distortion.prior_drift_deg_per_m is None and loc.distortion.prior_scale_error is None
    # everything else at the config's defaults
    plain = LocalizationConfig()
    assert loc.search == plain.search and loc.acceptance == plain.acceptance
    assert not loc.odometry_bounds_stated


def test_the_image_presets():
    loc = image_localization_config()
    assert (loc.search.epsilon_m, loc.search.epsilon_z_m, loc.refinement.radius_m) == (
        0.08,
        0.08,
        0.16,
    )
    assert (loc.acceptance.max_rmse_m, loc.acceptance.max_predicted_error_m) == (0.08, 0.15)
    assert loc.distortion.prior_drift_deg_per_m is None
    loop = image_loop_config()
    assert (loop.window_m, loop.window_target_landmarks, loop.window_max_m) == (8.0, 20, 12.0)
    assert loop.crop_sigma is CropSigma.SOURCE and IMAGE_WINDOW_M == 8.0


def test_overrides_apply_over_the_preset():
    loc = image_localization_config(odometry_scale_error=0.01, epsilon_m=0.06)
    assert loc.distortion.scale_error == 0.01 and loc.search.epsilon_m == 0.06
    assert loc.distortion.prior_drift_deg_per_m is None  # the rest of its section kept
    assert image_loop_config(window_m=6.0).window_max_m == 12.0


def test_every_preset_file_loads_and_unknown_names_are_refused():
    for name in PRESETS:
        assert isinstance(preset_table(name), dict)
    load_preset(LoopConfig, "image_loop")
    with pytest.raises(ConfigError, match="unknown preset"):
        preset_table("fast")
    with pytest.raises(ConfigError, match="unknown setting"):
        load_preset(LoopConfig, "image_localization")  # a localization preset is not a loop's
