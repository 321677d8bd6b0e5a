"""Verification: the named checks a pose must pass before it is claimed."""

from __future__ import annotations

import math
from dataclasses import dataclass

from lunarloc.localization.config import LocalizationConfig


@dataclass(frozen=True)
class Check:
    """One acceptance test of :func:`verify`: ``value`` must be ``relation`` (``"<="`` or
    ``">="``) ``limit``. ``detail`` is one line: the reason of the refusal when it fails,
    what was tested when it passes."""

    name: str
    value: float
    limit: float
    passed: bool
    relation: str = "<="
    detail: str = ""

    def to_dict(self) -> dict:
        def clean(x):
            return None if not math.isfinite(x) else float(x)

        return {
            "name": self.name,
            "value": clean(float(self.value)),
            "relation": self.relation,
            "limit": clean(float(self.limit)),
            "passed": bool(self.passed),
            "detail": self.detail,
        }


def _at_most(name: str, value: float, limit: float, fail: str, ok: str) -> Check:
    # NaN passes: a quantity that could not be measured refuses nothing here
    passed = not (value > limit)
    return Check(name, float(value), float(limit), passed, "<=", ok if passed else fail)


def _at_least(name: str, value: float, limit: float, fail: str, ok: str) -> Check:
    passed = not (value < limit)
    return Check(name, float(value), float(limit), passed, ">=", ok if passed else fail)


@dataclass
class Evidence:
    """What :func:`verify` judges: the quantities measured on the winning hypothesis.
    ``tilt_deg`` / ``handedness`` are None outside the gravity-aware mode (not tested)."""

    inliers: int
    rmse_m: float
    rmse_limit_m: float
    sigma_h_m: float
    sigma_z_m: float
    extent_m: float
    planarity: float
    tilt_deg: float | None
    handedness: float | None
    scale_error: float
    scale_se: float
    near_misses: int
    near_misses_expected: float
    near_inner_m: float
    near_outer_m: float
    predicted_error_m: float
    distortion_error_m: float
    predicted_rotation_deg: float
    distortion_rotation_deg: float
    inliers_beyond_chance: float
    required_inliers: int
    chance_inliers: float
    num_associations: int
    competitor: int
    distortion_fitted: bool = (
        False  # the distortion allowance was fitted from the maps, not from stated bounds
    )
    odometry_bounds: str = ""  # where the bounds came from (:class:`OdometryBounds` ``text``)


def verify(ev: Evidence, cfg: LocalizationConfig) -> list[Check]:
    """The acceptance tests of a hypothesis as a table of named checks, in the order their
    reasons are reported (the first failing check is the reason of a refusal). Every check is
    evaluated, so the table shows all that fail, not only the first. A pose is trusted only
    when every check passes."""
    out = [
        _at_most(
            "residual_rmse",
            ev.rmse_m,
            ev.rmse_limit_m,
            f"residual RMSE {ev.rmse_m * 100:.1f} cm exceeds {ev.rmse_limit_m * 100:.1f} cm (what "
            f"landmarks of {ev.sigma_h_m * 100:.1f} cm horizontal / {ev.sigma_z_m * 100:.1f} cm "
            "vertical uncertainty allow)",
            f"chi-square test of the inlier residuals at {cfg.acceptance.rmse_confidence:g} "
            "confidence",
        ),
        _at_least(
            "extent",
            ev.extent_m,
            cfg.acceptance.min_extent_m,
            f"inliers are clustered (extent {ev.extent_m:.2f} m < {cfg.acceptance.min_extent_m} m)",
            "inliers spread (2 x largest principal std, m)",
        ),
        _at_least(
            "planarity",
            ev.planarity,
            cfg.acceptance.min_planarity,
            "inliers are nearly collinear: rotation about their line is poorly fixed",
            "inliers not collinear (second / first principal std)",
        ),
    ]
    if ev.tilt_deg is not None:
        lim = cfg.search.max_tilt_deg + 0.5
        out.append(
            _at_most(
                "tilt",
                ev.tilt_deg,
                lim,
                f"fitted tilt {ev.tilt_deg:.2f} deg exceeds the allowed {cfg.search.max_tilt_deg} "
                "deg (mirror or wrong match)",
                "fitted tilt of the levelled map (deg)",
            )
        )
    if ev.handedness is not None:
        out.append(
            _at_least(
                "handedness",
                ev.handedness,
                cfg.acceptance.min_handedness,
                "inliers are a mirror image of the reference (triangle orientations disagree)",
                "share of inlier triangles with the reference's orientation",
            )
        )
    scale_lim = max(cfg.acceptance.max_scale_error, cfg.acceptance.scale_sigmas * ev.scale_se)
    out.append(
        _at_most(
            "scale",
            abs(ev.scale_error),
            scale_lim,
            f"vehicle map is not rigid: its inliers are {ev.scale_error * 100:+.1f} % larger than "
            f"the reference (+-{ev.scale_se * 100:.1f} %), as odometry scale drift makes them",
            "relative scale of the inliers against the reference",
        )
    )
    near_z = (ev.near_misses - ev.near_misses_expected) / math.sqrt(
        max(ev.near_misses_expected, 1.0)
    )
    near_ok = not (
        ev.near_misses >= cfg.acceptance.min_near_misses and near_z > cfg.acceptance.max_near_miss_z
    )
    out.append(
        Check(
            "near_misses",
            near_z,
            cfg.acceptance.max_near_miss_z,
            near_ok,
            "<=",
            "excess of landmarks just outside the inlier radius over chance (standard deviations; "
            f"{ev.near_misses} seen, {ev.near_misses_expected:.1f} expected)"
            if near_ok
            else f"vehicle map is not rigid: {ev.near_misses} of its landmarks land "
            f"{ev.near_inner_m * 100:.0f}-{ev.near_outer_m * 100:.0f} cm from a reference rock "
            f"where chance gives {ev.near_misses_expected:.1f} (scaled or bent by odometry drift "
            "away from the inliers)",
        )
    )
    source = ev.odometry_bounds or (
        "fitted from the maps, no odometry bounds stated"
        if ev.distortion_fitted
        else "from the odometry bounds"
    )
    out.append(
        _at_most(
            "predicted_error",
            cfg.acceptance.predicted_error_sigmas * ev.predicted_error_m,
            cfg.acceptance.max_predicted_error_m,
            "pose too uncertain where it is used: predicted error up to "
            f"{cfg.acceptance.predicted_error_sigmas:g} x {ev.predicted_error_m * 100:.1f} cm "
            f"(allowed {cfg.acceptance.max_predicted_error_m * 100:.0f} cm"
            + (
                # zero distortion: say where the bounds came from all the same
                f"; {ev.odometry_bounds}"
                if ev.distortion_error_m == 0 and ev.odometry_bounds
                else ""
                if ev.distortion_error_m == 0
                else f"; odometry distortion up to {ev.distortion_error_m * 100:.1f} cm, {source}"
            )
            + ")"
            + (
                ": the maps cannot show the odometry beyond the rocks they share; state its bounds "
                "(0 for a map built from ground-truth poses, or a file whose pose provenance says "
                "ground-truth) to judge with them"
                if ev.distortion_fitted and ev.distortion_error_m > 0
                else ""
            ),
            "predicted position error where the pose is used (m)",
        )
    )
    out.append(
        _at_most(
            "predicted_rotation",
            cfg.acceptance.predicted_error_sigmas * ev.predicted_rotation_deg,
            cfg.acceptance.max_predicted_rotation_deg,
            "heading too uncertain: predicted rotation error "
            f"{cfg.acceptance.predicted_error_sigmas:g} x {ev.predicted_rotation_deg:.2f} deg "
            f"(allowed {cfg.acceptance.max_predicted_rotation_deg:g} deg; odometry heading drift "
            f"up to {ev.distortion_rotation_deg:.2f} deg, {source})",
            "predicted rotation error (deg)",
        )
    )
    out.append(
        _at_least(
            "inliers_vs_chance",
            ev.inliers_beyond_chance,
            ev.required_inliers,
            f"{ev.inliers} inliers ({ev.inliers_beyond_chance:.1f} when refinement's chance "
            f"matches are discounted) is too few to beat chance at {ev.num_associations} "
            f"associations (need {ev.required_inliers}; unrelated maps of this size give up to "
            f"~{ev.chance_inliers:.0f})",
            "inliers (refinement's chance matches discounted) against the chance envelope plus "
            "margin",
        )
    )
    out.append(
        _at_least(
            "winner_margin",
            ev.inliers,
            cfg.acceptance.competitor_ratio * ev.competitor,
            f"ambiguous: {ev.inliers} inliers vs a competing hypothesis with {ev.competitor}",
            f"inliers against {cfg.acceptance.competitor_ratio:g} x the best competing hypothesis",
        )
    )
    return out
