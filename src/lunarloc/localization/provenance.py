"""Where the vehicle map's odometry distortion bounds come from, in one order of precedence:

1. **stated**: the configuration (``LocalizationConfig.distortion.scale_error`` /
   ``heading_drift_deg_per_m``; the CLI's ``--odometry-scale-error`` /
   ``--odometry-drift`` or a ``--config`` file) says them;
2. **the map's pose provenance** (:class:`lunarloc.io.maps.PoseProvenance`, read from its file): a
   map placed by ground-truth poses is rigid, bounds 0 (a LunarLoc dataset traverse CSV, whose
   schema says its detections carry the ground-truth pose, and any file that states
   ``ground-truth``);
3. **the prior**: a map placed by odometry, or one that says nothing, has no bounds; its
   distortion is fitted from the maps under the prior of real rover odometry
   (``odometry_prior_drift_deg_per_m``, ``odometry_prior_scale_error``; docs/verification.md).

:func:`resolve_odometry_bounds` applies it; :func:`lunarloc.localize` calls it first, and its
result (:attr:`LocalizationResult.odometry_bounds`) and refusal text say which one judged the pose.
A user who states a bent map rigid (or writes ``ground-truth`` into an odometry-built file) gets
that map judged rigid: the scale and near-miss checks still run on it.
"""

from __future__ import annotations

from dataclasses import dataclass

from lunarloc.io.maps import LandmarkMap, PoseProvenance
from lunarloc.localization.config import LocalizationConfig

__all__ = ["OdometryBoundsOrigin", "resolve_odometry_bounds", "STATED", "PROVENANCE", "PRIOR"]

STATED = "stated"  # the configuration states the bounds
PROVENANCE = "pose provenance"  # the map's file says its poses were the ground truth: bounds 0
PRIOR = "prior"  # no bounds: fitted from the maps under the odometry prior


@dataclass(frozen=True)
class OdometryBoundsOrigin:
    """The odometry distortion bounds a localization used, and where they came from.

    ``source``: :data:`STATED`, :data:`PROVENANCE` or :data:`PRIOR`. ``scale_error`` and
    ``heading_drift_deg_per_m``: the bounds (None for the prior: fitted). ``pose_provenance``:
    what the vehicle map's file says (None: nothing), whichever source won. ``text``: one line
    for people, e.g. ``odometry bounds: 0 (rigid), from the map's pose provenance: ground truth
    (the file's pose column)``."""

    source: str
    scale_error: float | None
    heading_drift_deg_per_m: float | None
    pose_provenance: PoseProvenance | None
    text: str

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "scale_error": self.scale_error,
            "heading_drift_deg_per_m": self.heading_drift_deg_per_m,
            "pose_provenance": None
            if self.pose_provenance is None
            else self.pose_provenance.to_dict(),
            "text": self.text,
        }


def _bounds_text(scale: float | None, drift: float | None) -> str:
    if not scale and not drift:
        return "0 (rigid)"
    return f"scale error {(scale or 0.0) * 100:g} %, heading drift {drift or 0.0:g} deg/m"


def resolve_odometry_bounds(
    config: LocalizationConfig, vehicle: LandmarkMap
) -> tuple[LocalizationConfig, OdometryBoundsOrigin]:
    """`config` with the odometry bounds that judge `vehicle` (stated > the map's pose provenance
    > the prior; module docstring), and the record of where they came from."""
    prov = getattr(vehicle, "pose_provenance", None)
    if config.odometry_bounds_stated:
        s, d = config.distortion.scale_error, config.distortion.heading_drift_deg_per_m
        return config, OdometryBoundsOrigin(
            STATED,
            s,
            d,
            prov,
            f"odometry bounds: {_bounds_text(s, d)}, stated in the configuration",
        )
    if prov is not None and prov.rigid:
        cfg = config.with_settings(distortion={"scale_error": 0.0, "heading_drift_deg_per_m": 0.0})
        return cfg, OdometryBoundsOrigin(
            PROVENANCE,
            0.0,
            0.0,
            prov,
            f"odometry bounds: 0 (rigid), from the map's pose provenance: {prov.describe()}",
        )
    if (
        config.distortion.prior_drift_deg_per_m is None
        and config.distortion.prior_scale_error is None
    ):
        how = "fitted from the maps alone (no prior configured)"
    else:
        how = (
            "fitted from the maps, under the prior of real rover odometry ("
            f"{config.distortion.prior_drift_deg_per_m or 0:g} deg/m, "
            f"{(config.distortion.prior_scale_error or 0) * 100:g} %) where its path is given"
        )
    why = (
        "the map states no pose provenance"
        if prov is None
        else f"the map's pose provenance is {prov.describe()}"
    )
    return config, OdometryBoundsOrigin(
        PRIOR, None, None, prov, f"no odometry bounds: {how}; {why}"
    )
