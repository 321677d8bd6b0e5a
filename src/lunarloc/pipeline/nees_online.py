"""Is the online loop's stated uncertainty honest? The normalised estimation error squared (NEES)
of (a) the loop's fixes, before the pose graph's floors, and (b) the online estimate's
``covariance`` along a run.

NEES: the position error's squared Mahalanobis distance under the stated 3x3 position
covariance, 3 degrees of freedom. A calibrated covariance puts 60-80 % of the cases under 3.53
(the 68.3 % quantile of chi-square(3)) and at least 99 % under 14.16 (99.73 %).

- :func:`loop_fix_records`: the loop (:func:`lunarloc.pipeline.runner.run`, as ``lunarloc bench
  loop`` runs it) on real traverses, each against a map of all the others; one record per
  successful localization: its error against the truth and the covariance ``localize()`` states
  for it at the rover (:attr:`lunarloc.online.loop.Attempt.fix_covariance_xyz`).
- :func:`site_fix_records`: the same records for the image loop (``RunConfig()``: detections
  from simulated stereo images) on recorded LAC-look sites (``benchmarks/bench_lac_map.py
  simulate``: a ``traverse.lac`` archive and the site's ``rocks.csv`` as the reference).
- :func:`trace_nees`: the NEES of every localized tick of a per-tick trace (true and estimated
  positions, covariance), such as ``benchmarks/bench_lac_leaderboard.py`` writes.
- :func:`nees_shares`: the two shares; :func:`yaw_nees_shares`: the heading's (1 dof: 68.3 %
  under 1.0, 99.73 % under 9.0).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from lunarloc.config.run import RunConfig

__all__ = [
    "NEES1_68",
    "NEES1_997",
    "NEES_68",
    "NEES_997",
    "loop_fix_records",
    "nees",
    "nees_shares",
    "site_fix_records",
    "trace_nees",
    "yaw_nees_shares",
]

NEES_68 = 3.5267  # chi-square, 3 dof: 68.27 % quantile
NEES_997 = 14.156  # 99.73 % quantile
NEES1_68 = 1.0  # chi-square, 1 dof (a heading): 68.27 % quantile
NEES1_997 = 9.0  # 99.73 % quantile


def nees(error_xyz, covariance_xyz) -> np.ndarray:
    """NEES of each error (n, 3) under its 3x3 covariance (n, 3, 3); NaN where the covariance
    is not finite or singular."""
    E = np.asarray(error_xyz, float).reshape(-1, 3)
    C = np.asarray(covariance_xyz, float).reshape(-1, 3, 3)
    out = np.full(len(E), math.nan)
    for i, (e, c) in enumerate(zip(E, C)):
        if np.all(np.isfinite(c)) and np.all(np.isfinite(e)):
            try:
                out[i] = float(e @ np.linalg.solve(c, e))
            except np.linalg.LinAlgError:
                pass
    return out


def nees_shares(
    values: Iterable[float], quantiles: tuple[float, float] = (NEES_68, NEES_997)
) -> tuple[int, float, float]:
    """(cases, share under 3.53, share under 14.16) of the finite NEES values (NaN shares for
    none); `quantiles` for another number of degrees of freedom."""
    v = np.asarray(list(values), float)
    v = v[np.isfinite(v)]
    if not len(v):
        return 0, math.nan, math.nan
    lo, hi = quantiles
    return len(v), float(np.mean(v < lo)), float(np.mean(v < hi))


def yaw_nees_shares(values: Iterable[float]) -> tuple[int, float, float]:
    """(cases, share under 1.0, share under 9.0) of the finite 1-dof NEES values (a heading's:
    ``(error / sigma)^2``; NaN shares for none)."""
    return nees_shares(values, (NEES1_68, NEES1_997))


def _fix_record(a, loop_config, **extra) -> dict:
    """One successful localization's record (:func:`loop_fix_records`)."""
    from lunarloc.online.loop import fix_model_terms, fix_model_yaw_variance, inlier_radius_m

    e, C = np.array(a.fix_error_xyz), np.array(a.fix_covariance_xyz)
    C0 = C - fix_model_terms(
        a.fix_distortion_m,
        a.fix_maps_from_detections,
        loop_config,
        a.fix_yaw_rad,
        a.fix_carried_path_m,
    )
    ey, sy = float(a.fix_error_yaw_rad), float(a.fix_sigma_yaw_rad)
    inl = np.asarray(a.inlier_vehicle_xyz or np.zeros((0, 3)), float).reshape(-1, 3)
    model_yaw = fix_model_yaw_variance(
        a.fix_distortion_yaw_rad,
        inl,
        a.fix_maps_from_detections,
        loop_config,
        a.fix_since_fix_s,
        a.fix_graph_bias_turn_rad,
    )
    sy0 = math.sqrt(max(sy * sy - model_yaw, 0.0))
    return {
        **extra,
        "keyframe": a.keyframe,
        "time_s": a.time_s,
        "accepted": a.accepted,
        "inliers": a.inliers,
        "predicted_error_m": a.predicted_error_m,
        "distortion_m": a.fix_distortion_m,
        "window_m": a.window_m,
        "error_xyz": e.tolist(),
        "covariance_xyz": C.tolist(),
        "nees": float(nees(e, C)[0]),
        # localize()'s own covariance at the rover, before the loop's model
        "covariance_localize_xyz": C0.tolist(),
        "nees_localize": float(nees(e, C0)[0]),
        "maps_from_detections": a.fix_maps_from_detections,
        # the heading: error (rad) and the sigma stated for it; 1-dof NEES
        "error_yaw_rad": ey,
        "sigma_yaw_rad": sy,
        "nees_yaw": (ey / sy) ** 2 if sy > 0 else math.nan,
        # localize()'s own yaw sigma (before the loop's model, fix_model_yaw_variance), its
        # heading-drift allowance and the inliers' rms horizontal radius (m)
        "sigma_yaw_localize_rad": sy0,
        "nees_yaw_localize": (ey / sy0) ** 2 if sy0 > 0 else math.nan,
        "distortion_yaw_rad": a.fix_distortion_yaw_rad,
        "inlier_radius_m": inlier_radius_m(inl),
        "heading_yaw_rad": a.fix_yaw_rad,
        "since_fix_s": a.fix_since_fix_s,
        # the graph's predicted heading growth since its last solve (rad^2): from its bias's
        # marginal, from its process noise; the inliers' mean ray (m, map frame) and range (m)
        "graph_yaw_var_bias_rad2": a.fix_graph_yaw_var_bias_rad2,
        "graph_yaw_var_process_rad2": a.fix_graph_yaw_var_process_rad2,
        "graph_bias_turn_rad": a.fix_graph_bias_turn_rad,
        "since_fix_m": a.fix_since_fix_m,
        "ray_xy_m": a.fix_ray_xy_m,
        "range_m": a.fix_range_m,
        # the path (m) the odometry's prediction alone carried the inliers' sightings
        "carried_path_m": a.fix_carried_path_m,
    }


def loop_fix_records(
    data: str | Path,
    traverses: Iterable[int] | None = None,
    config: RunConfig | None = None,
    min_length_m: float = 5.0,
) -> list[dict]:
    """Run the loop on each traverse of `data` (default all) against the others, as ``lunarloc
    bench loop`` does (``config`` default :meth:`RunConfig.for_detections`: simulated drift
    0.05 deg/m and 2 % scale), and return one record per successful localization: vehicle,
    keyframe, accepted by the gate, inliers, predicted error (m), distortion allowance (m), the
    fix's error (3,) and stated position covariance (3, 3) at the rover and its NEES,
    localize()'s own covariance there and its NEES (before the loop's model,
    :func:`lunarloc.online.loop.fix_model_terms`), and the heading's error, stated sigma and
    1-dof NEES."""
    from lunarloc.io.maps import load_traverse
    from lunarloc.pipeline.evaluation import find_traverses
    from lunarloc.pipeline.reference import reference_from_traverses
    from lunarloc.pipeline.runner import run
    from lunarloc.pipeline.sources import TraverseCsvSource

    cfg = config or RunConfig.for_detections()
    trav = {k: load_traverse(p) for k, p in find_traverses(data).items()}
    out = []
    for v in sorted(trav) if traverses is None else list(traverses):
        if trav[v].path_length < min_length_m:
            continue
        src = TraverseCsvSource.for_run(trav[v], cfg)
        res = run(src, reference_from_traverses(trav, exclude=v), cfg)
        for a in res.attempts:
            if a.success and a.fix_error_xyz is not None and a.fix_covariance_xyz is not None:
                out.append(_fix_record(a, cfg.loop, vehicle=v))
    return out


def site_fix_records(sites: Iterable[str | Path], config: RunConfig | None = None) -> list[dict]:
    """Run the image loop (``config`` default ``RunConfig()``: the detector on the archive's
    stereo pairs, the visual odometry, the ``image_loop`` preset) on each recorded site folder
    (``traverse.lac`` and the reference ``rocks.csv``, as ``benchmarks/bench_lac_map.py
    simulate`` writes them) and return one record per successful localization, as
    :func:`loop_fix_records` (``site``: the folder's name)."""
    from lunarloc.core.errors import InputError
    from lunarloc.pipeline.reference import load_reference
    from lunarloc.pipeline.runner import run
    from lunarloc.pipeline.sources import ArchiveSource

    cfg = config or RunConfig()
    out = []
    for d in map(Path, sites):
        if not (d / "traverse.lac").is_file() or not (d / "rocks.csv").is_file():
            raise InputError(f"{d}: a site folder holds traverse.lac and rocks.csv")
        src = ArchiveSource(d / "traverse.lac", cfg.odometry, cfg.detector.pairs)
        res = run(src, load_reference(d / "rocks.csv"), cfg)
        for a in res.attempts:
            if a.success and a.fix_error_xyz is not None and a.fix_covariance_xyz is not None:
                out.append(_fix_record(a, cfg.loop, site=d.name))
    return out


def trace_nees(trace, localized_only: bool = True) -> np.ndarray:
    """NEES of every tick of a trace (a mapping with ``truth_xyz``, ``est_xyz`` (n, 3),
    ``covariance_xyz`` (n, 3, 3) and ``localized`` (n,)), of the localized ticks only unless
    `localized_only` is False."""
    e = np.asarray(trace["est_xyz"], float) - np.asarray(trace["truth_xyz"], float)
    v = nees(e, trace["covariance_xyz"])
    return v[np.asarray(trace["localized"], bool)] if localized_only else v
