"""What is not a rock: the detector's rejection rules as a table of small named predicates.

The detector (STEREO_POINTS) measures each candidate blob once (:class:`BlobMeasures`: its
radius, its heights above the ground three ways, the share of nearer surface around it, how
far its height goes on beyond its ends, the roughness of its disparity), then runs every rule
of :data:`RULES` over those measures. A rule that fires rejects the blob (NOT_A_ROCK), except
that a *tentative* rule (``Rule.tentative``) lets a mid-range blob through as a tentative
detection, to be confirmed by a neighbouring frame. A rule is switched off by naming it in
``DetectorConfig.rules.off`` (most also have a threshold whose 0 switches them off).

Each predicate takes the measures and the rules' settings (:class:`~lunarloc.perception.
detector_config.RulesConfig`, or anything with its attribute names) and returns a bool; NaN
measures never fire a rule, except the strip rule's (a strip must prove it ends at its sides).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from lunarloc.perception.masks import MaskFilterConfig, MaskStats, RejectReason

__all__ = [
    "BlobMeasures",
    "Rule",
    "RULES",
    "RULE_NAMES",
    "TENTATIVE_RULES",
    "fired_rules",
    "is_flat_strip",
    "is_raised_strip",
    "strip_rejected",
]


@dataclass(frozen=True)
class BlobMeasures:
    """What the rules judge a candidate blob by (rover frame, metres)."""

    radius_m: float  # estimated radius R
    # how high it stands: its visible top or extent, or its height above the ground in front
    visible_height_m: float
    top_m: float  # its visible top above the local ground
    front_m: float  # its visible top above the ground in front of it (NaN: too few points there)
    ring_m: float  # upper quartile of the heights in the ring around it (NaN: none)
    quadric_m: (
        float  # its visible top above a quadric ground fitted around it (NaN: too few points)
    )
    nearer_fraction: (
        float  # share of the ring's upper half nearer than nearer_depth_ratio x its depth (NaN)
    )
    extension_ratio: (
        float  # how far its height goes on beyond its ends, over its top (NaN: not measured)
    )
    # share of rough second differences of its full-resolution disparity (NaN: not measured)
    roughness: float
    strip: bool = False  # let through the image filters as a flat strip (is_flat_strip)
    raised: bool = False  # ... as a raised strip candidate (is_raised_strip)
    # upper quantile of the image gradient over it and its rim (grey levels per pixel; NaN: not
    # measured)
    image_gradient: float = float("nan")
    depth_m: float = float("nan")  # its median depth (optical z; NaN: not known)


@dataclass(frozen=True)
class Rule:
    """One rejection rule: its name, whether a mid-range blob may survive it as a tentative
    detection, and its predicate ``fires(measures, rules_config) -> bool``."""

    name: str
    tentative: bool
    fires: Callable[[BlobMeasures, Any], bool]


def too_tall(b: BlobMeasures, c) -> bool:
    """Standing higher than any rock (the lander's deck, tanks and panels stand 1-3 m)."""
    return b.visible_height_m > c.max_rock_height_m


def too_wide(b: BlobMeasures, c) -> bool:
    """Wider than any rock (LAC rocks have radii up to ~1 m)."""
    return b.radius_m > c.max_rock_radius_m


def perched(b: BlobMeasures, c) -> bool:
    """A small blob standing far higher than its size allows, above the ground in front of it
    or above the local ground: a knob on something larger (a boulder, the lander). A blob of
    radius perched_max_radius_m or more is never judged (a boulder taller than wide, end-on)."""
    out = False
    if math.isfinite(b.front_m):
        out = b.front_m > c.height_per_radius * b.radius_m + c.height_margin_m
    out |= b.top_m > c.top_per_radius * b.radius_m + c.top_noise_m
    out &= not (0 < c.perched_max_radius_m <= b.radius_m)
    return bool(out)


def framed(b: BlobMeasures, c) -> bool:
    """Framed from above by a nearer surface: on (or a mismatch on) a boulder's face nearby."""
    return bool(math.isfinite(b.nearer_fraction) and b.nearer_fraction > c.max_nearer_ring_fraction)


def rough(b: BlobMeasures, c) -> bool:
    """A patchwork of disparities: stereo noise in a textureless shadow, not a smooth surface."""
    return bool(b.roughness > c.max_disparity_roughness)


def contrast(b: BlobMeasures, c) -> bool:
    """Hardly standing out of the ring of ground around it: a stretch of crest."""
    return bool(math.isfinite(b.ring_m) and b.top_m - b.ring_m < c.min_contrast_m)


def quadric(b: BlobMeasures, c) -> bool:
    """Hardly standing out of a quadric ground fitted around it (which follows a crest or rim)."""
    return bool(
        math.isfinite(b.quadric_m)
        and b.quadric_m < min(c.quadric_contrast_per_radius * b.radius_m, c.quadric_contrast_max_m)
    )


def crest(b: BlobMeasures, c) -> bool:
    """Its height goes on beyond its left and right ends (a crest's local high), but not far
    higher (a larger raised body beside it)."""
    r = c.crest_extension_ratio
    return bool(r > 0 and r < b.extension_ratio <= c.crest_extension_max_ratio)


def featureless(b: BlobMeasures, c) -> bool:
    """Hardly showing in the image (no edge of a lit face, shaded side, outline or shadow) and
    with the ground around it rising with it: a bump of smooth regolith that stereo lifts out
    of the ground (a hummock, a gentle rim). A blob standing featureless_max_quadric_m or more
    above the quadric ground is not judged (the plain face of a large rock), nor one whose
    ring of ground stays low (a rock in shadow on level ground), nor one nearer than
    featureless_min_depth_m (a near rock's mask is large and its outline a small part of it)."""
    return bool(
        math.isfinite(b.image_gradient)
        and math.isfinite(b.depth_m)
        and b.depth_m >= c.featureless_min_depth_m
        and b.image_gradient < c.min_image_gradient
        and math.isfinite(b.ring_m)
        and b.ring_m >= c.featureless_min_ring_m
        and not (math.isfinite(b.quadric_m) and b.quadric_m >= c.featureless_max_quadric_m)
    )


def strip(b: BlobMeasures, c) -> bool:
    """An elongated blob let through as a strip that fails its strip test (strip_rejected)."""
    return strip_rejected(b.strip, b.raised, b.extension_ratio, b.quadric_m, b.radius_m, c)


#: The rules, in the order they are run (and a tentative detection's rules are named).
RULES: tuple[Rule, ...] = (
    Rule("too_tall", False, too_tall),
    Rule("too_wide", False, too_wide),
    Rule("perched", False, perched),
    Rule("framed", False, framed),
    Rule("rough", False, rough),
    Rule("featureless", False, featureless),
    Rule("contrast", True, contrast),
    Rule("quadric", True, quadric),
    Rule("crest", True, crest),
    Rule("strip", True, strip),
)
RULE_NAMES: tuple[str, ...] = tuple(r.name for r in RULES)
#: The verdicts a mid-range blob may survive as a tentative detection.
TENTATIVE_RULES = frozenset(r.name for r in RULES if r.tentative)


def fired_rules(b: BlobMeasures, c) -> tuple[list[str], list[str]]:
    """(hard, soft): the names of the rules (not switched off in ``c.off``) that fire on `b`;
    hard ones reject it, soft (tentative) ones let a mid-range blob through as tentative."""
    off = getattr(c, "off", ())
    hard, soft = [], []
    for rule in RULES:
        if rule.name not in off and rule.fires(b, c):
            (soft if rule.tentative else hard).append(rule.name)
    return hard, soft


# ---------------------------------------------------------------------- strips
def is_flat_strip(reason: RejectReason | None, st: MaskStats, fc: MaskFilterConfig, c) -> bool:
    """True for a mask the image filters reject as elongated only, with an eigenvalue ratio
    within c.strip_max_eig_ratio (a small rock's flat top strip at mid range)."""
    return (
        reason is RejectReason.ELONGATED
        and c.strip_max_eig_ratio > fc.tau_elong
        and st.eig_ratio <= c.strip_max_eig_ratio
    )


def is_raised_strip(reason: RejectReason | None, st: MaskStats, fc: MaskFilterConfig, c) -> bool:
    """True for a mask the image filters reject as elongated only, with an eigenvalue ratio
    within c.raised_strip_max_eig_ratio and at least c.raised_strip_min_area_px pixels."""
    return (
        reason is RejectReason.ELONGATED
        and c.raised_strip_max_eig_ratio > fc.tau_elong
        and st.eig_ratio <= c.raised_strip_max_eig_ratio
        and st.area >= c.raised_strip_min_area_px
    )


def strip_rejected(strip: bool, raised: bool, ext: float, quad: float, radius_m: float, c) -> bool:
    """Whether an elongated mask let through as a flat strip (`strip`) and/or a raised strip
    candidate (`raised`) is still rejected: kept when it is a flat strip that ends at its sides
    (extension ratio `ext` <= c.strip_max_extension_ratio) or a raised strip whose top stands
    >= c.raised_strip_min_quadric_m above the quadric ground (`quad`, metres) with an estimated
    radius `radius_m` <= c.raised_strip_max_radius_m. NaN measures fail their test. False for a
    mask that is neither."""
    if not (strip or raised):
        return False
    if strip and ext <= c.strip_max_extension_ratio:
        return False
    return not (
        raised and quad >= c.raised_strip_min_quadric_m and radius_m <= c.raised_strip_max_radius_m
    )
