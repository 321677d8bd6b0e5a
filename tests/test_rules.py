"""The detector's rejection rules (perception/rules.py) one by one, their switch (rules.off), and
the sectioned DetectorConfig: declarative ranges, round trips, and the flat keys of older files."""

from __future__ import annotations

import functools
import json
import math
import operator
from dataclasses import fields, replace
from pathlib import Path

import pytest

from lunarloc.core.configs import config_from_dict, config_to_dict
from lunarloc.core.errors import ConfigError
from lunarloc.perception.detector import DetectorConfig
from lunarloc.perception.detector_config import MOVED_KEYS, RulesConfig
from lunarloc.perception.rules import (
    RULE_NAMES,
    RULES,
    TENTATIVE_RULES,
    BlobMeasures,
    fired_rules,
)
from lunarloc.perception.segment import ClassicalConfig
from lunarloc.perception.small_rocks import SmallRockConfig

NAN = float("nan")
C = RulesConfig(min_image_gradient=5.0)  # the featureless rule on (off by default)
# a plain rock: 0.1 m radius, 0.08 m high, standing out of everything around it
ROCK = BlobMeasures(
    radius_m=0.1,
    visible_height_m=0.08,
    top_m=0.08,
    front_m=0.1,
    ring_m=0.0,
    quadric_m=0.06,
    nearer_fraction=0.0,
    extension_ratio=0.1,
    roughness=0.02,
    image_gradient=20.0,
    depth_m=3.0,
)
# per rule: measures that make it fire (and only it, on the plain rock)
FIRING = {
    "too_tall": {"visible_height_m": C.max_rock_height_m + 0.1},
    "too_wide": {
        "radius_m": C.max_rock_radius_m + 0.1,
        "quadric_m": 1.0,
        "front_m": 0.5,
        "top_m": 0.5,
        "visible_height_m": 0.5,
    },
    "perched": {"front_m": C.height_per_radius * 0.1 + C.height_margin_m + 0.05},
    "framed": {"nearer_fraction": C.max_nearer_ring_fraction + 0.1},
    "rough": {"roughness": C.max_disparity_roughness + 0.1},
    "featureless": {"image_gradient": C.min_image_gradient / 2, "ring_m": C.featureless_min_ring_m},
    "contrast": {"ring_m": 0.08 - C.min_contrast_m / 2},
    "quadric": {
        "quadric_m": 0.5 * min(C.quadric_contrast_per_radius * 0.1, C.quadric_contrast_max_m)
    },
    "crest": {"extension_ratio": 0.5 * (C.crest_extension_ratio + C.crest_extension_max_ratio)},
    "strip": {"strip": True, "extension_ratio": C.strip_max_extension_ratio + 0.05},
}


def test_the_plain_rock_passes_every_rule():
    assert fired_rules(ROCK, C) == ([], [])


def test_every_rule_has_a_firing_case():
    assert set(FIRING) == set(RULE_NAMES) and len(RULE_NAMES) == len(set(RULE_NAMES))


@pytest.mark.parametrize("name", RULE_NAMES)
def test_each_rule_fires_alone_and_is_switched_off_by_name(name):
    b = replace(ROCK, **FIRING[name])
    hard, soft = fired_rules(b, C)
    assert hard + soft == [name]
    assert (soft == [name]) == (name in TENTATIVE_RULES)
    assert fired_rules(b, replace(C, off=(name,))) == ([], [])


@pytest.mark.parametrize("name", sorted(set(RULE_NAMES) - {"strip"}))
def test_nan_measures_fire_no_rule(name):
    b = BlobMeasures(
        radius_m=0.1,
        visible_height_m=NAN,
        top_m=NAN,
        front_m=NAN,
        ring_m=NAN,
        quadric_m=NAN,
        nearer_fraction=NAN,
        extension_ratio=NAN,
        roughness=NAN,
    )
    assert name not in functools.reduce(operator.iadd, fired_rules(b, C), [])


def test_a_strip_must_prove_it_ends_at_its_sides():
    b = replace(ROCK, strip=True, extension_ratio=NAN)
    assert fired_rules(b, C) == ([], ["strip"])
    assert fired_rules(replace(b, extension_ratio=C.strip_max_extension_ratio), C) == ([], [])


def test_perched_spares_a_boulder_and_judges_every_blob_at_zero():
    high = {"front_m": 2.0, "top_m": 0.9, "visible_height_m": 0.9, "quadric_m": 0.9}
    boulder = replace(ROCK, radius_m=C.perched_max_radius_m, **high)
    assert "perched" not in fired_rules(boulder, C)[0]
    assert "perched" in fired_rules(boulder, replace(C, perched_max_radius_m=0.0))[0]


def test_featureless_spares_a_rock_on_level_ground_and_a_tall_plain_face():
    # no edge in the image, but the ground around it stays low: a rock in shadow on level ground
    dark = replace(ROCK, image_gradient=C.min_image_gradient / 2)
    assert fired_rules(replace(dark, ring_m=C.featureless_min_ring_m / 2), C) == ([], [])
    # ... or standing high above the quadric ground: the plain face of a large rock
    raised = replace(dark, ring_m=C.featureless_min_ring_m, quadric_m=C.featureless_max_quadric_m)
    assert fired_rules(raised, C) == ([], [])
    # a smooth bump on rising ground that shows a little more edge than the threshold is kept
    edged = replace(dark, ring_m=C.featureless_min_ring_m, image_gradient=C.min_image_gradient)
    assert fired_rules(edged, C) == ([], [])
    # near blobs are not judged (a near rock's outline is a small part of its large mask)
    near = replace(dark, ring_m=C.featureless_min_ring_m, depth_m=C.featureless_min_depth_m / 2)
    assert fired_rules(near, C) == ([], [])
    assert fired_rules(replace(near, depth_m=C.featureless_min_depth_m), C) == (["featureless"], [])


def test_the_thresholds_off_values_switch_their_rules_off():
    for name, off in (
        ("crest", {"crest_extension_ratio": 0.0}),
        ("quadric", {"quadric_contrast_per_radius": 0.0}),
        ("framed", {"max_nearer_ring_fraction": 1.0}),
        ("rough", {"max_disparity_roughness": 1.0}),
        ("featureless", {"min_image_gradient": 0.0}),
    ):
        b = replace(ROCK, **FIRING[name])
        if name == "rough":
            b = replace(b, roughness=1.0)
        assert fired_rules(b, replace(C, **off)) == ([], []), name


def test_unknown_rule_names_are_refused():
    with pytest.raises(ConfigError, match="nonesuch"):
        RulesConfig(off=("nonesuch",))
    cfg = config_from_dict(DetectorConfig, {"rules": {"off": ["crest", "strip"]}})
    assert cfg.rules.off == ("crest", "strip")


def test_rule_table_order_names_tentatives_as_before():
    assert [r.name for r in RULES if r.tentative] == ["contrast", "quadric", "crest", "strip"]


# ---------------------------------------------------------------------- the config
def test_detector_config_round_trips_through_json():
    cfg = DetectorConfig(
        fuse_tol_m=0.2, centre_estimator="blend", rules=RulesConfig(off=("crest",))
    )
    d = json.loads(json.dumps(cfg.to_dict()))
    assert config_from_dict(DetectorConfig, d) == cfg
    assert config_to_dict(config_from_dict(DetectorConfig, d)) == d
    import copy
    import pickle

    assert (
        pickle.loads(pickle.dumps(cfg)) == cfg and copy.deepcopy(cfg) == cfg
    )  # the flat-key reads stay out of the way


def test_every_section_field_has_a_declared_range_or_is_not_a_number():
    for section in (
        "level",
        "depth_split",
        "centre",
        "points",
        "rules",
        "confirm",
        "tentative",
        "track_fusion",
    ):
        sec = getattr(DetectorConfig(), section)
        for f in fields(sec):
            if isinstance(getattr(sec, f.name), (int, float)):
                assert "range" in f.metadata, f"{section}.{f.name}"


@pytest.mark.parametrize(
    "data, key",
    [
        ({"centre": {"near_weight": 1.5}}, "near_weight"),
        ({"track_fusion": {"max_frames": 0}}, "max_frames"),
        ({"tentative": {"min_views": 3}}, "min_views"),
        ({"level": {"min_deg": 90.0}}, "min_deg"),
        ({"rules": {"max_disparity_roughness": 0.0}}, "max_disparity_roughness"),
        ({"points": {"p1_per_block_px2": 40}}, "p1_per_block_px2"),
        ({"fastsam_imgsz_px": 1000}, "fastsam_imgsz_px"),
        ({"level": {"from_stereo": 1}}, "from_stereo"),
        ({"depth_split": {"step_px": 1.5}}, "step_px"),
    ],
)
def test_ranges_are_checked_when_loaded(data, key):
    with pytest.raises(ConfigError, match=key):
        config_from_dict(DetectorConfig, data)


def test_ranges_are_checked_when_built_in_code():
    with pytest.raises(ConfigError, match="near_weight"):
        replace(DetectorConfig().centre, near_weight=-0.1)
    with pytest.raises(ConfigError, match="tol_m"):
        DetectorConfig(fuse_tol_m=math.inf)


def test_old_flat_keys_load_and_read_as_before():
    old = json.loads(
        (Path(__file__).parent / "data" / "run_config_flat_detector.json").read_text()
    )["detector"]
    cfg = config_from_dict(DetectorConfig, old)
    assert cfg.track_fusion.tol_m == 0.2 and cfg.centre.estimator.value == "blend"
    assert (
        cfg.tentative.min_repeats == 4
        and cfg.level.min_deg == 5.0
        and cfg.rules.crest_extension_ratio == 0.5
    )
    assert cfg.points.span_px == 32
    # every other setting as the file gives it, read through the old names
    for k, v in old.items():
        if k in MOVED_KEYS:
            assert config_to_dict(getattr(cfg, k)) == v, k
    # the small-rock and segmenter sections as the file saved them (their defaults have moved
    # since: the small-rock stage, the height-saddle split)
    small = config_from_dict(SmallRockConfig, old["small_rocks"])
    classical = config_from_dict(ClassicalConfig, old["classical"])
    assert cfg == DetectorConfig(
        fuse_tol_m=0.2,
        centre_estimator="blend",
        tentative_min_repeats=4,
        level_min_deg=5.0,
        crest_extension_ratio=0.5,
        fullres_span_px=32,
        small_rocks=small,
        classical=classical,
    )


def test_a_key_given_flat_and_in_its_section_is_refused():
    with pytest.raises(ConfigError, match="given twice"):
        config_from_dict(DetectorConfig, {"fuse_tol_m": 0.2, "track_fusion": {"tol_m": 0.1}})


def test_a_whole_old_run_config_loads(tmp_path):
    from lunarloc.config.run import RunConfig, load_config_file

    src = Path(__file__).parent / "data" / "run_config_flat_detector.json"
    cfg, _ = load_config_file(src)
    assert cfg.detector.track_fusion.tol_m == 0.2
    p = tmp_path / "config.json"
    p.write_text(json.dumps(cfg.to_dict()))
    assert load_config_file(p)[0] == cfg and RunConfig.from_dict(cfg.to_dict()) == cfg
