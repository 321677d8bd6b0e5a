"""One-shot global localization of a vehicle landmark map in a reference map.

``localize(reference, vehicle, config) -> LocalizationResult``:

1. putative associations (all-to-all, optionally pruned by size);
2. sparse consistency graph(s) (:mod:`lunarloc.association.graph`);
3. densest consistent set: exact maximum clique (default) or CLIPPER relaxation;
4. registration: Arun's SVD on the inliers, then optional refinement with the
   mutual nearest neighbours under the estimate;
5. verification: inliers vs. what chance produces at this map size, residual RMSE,
   spread of the inliers, fitted tilt and handedness (gravity mode), and the margin
   over the best competing hypothesis. ``success`` is False, with a reason, when the
   answer cannot be trusted.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np

from lunarloc.association.putative import putative_associations
from lunarloc.core.errors import DegenerateGeometryError, InputError
from lunarloc.core.geometry import (
    as_points,
    tilt_angle,
    transform_points,
    yaw_of,
)
from lunarloc.io.maps import LandmarkMap
from lunarloc.localization.bending import (
    PRIOR_CONFLICT_SIGMAS,
    bending_fit,
    fitted_predicted_error,
    prior_conflict,
)
from lunarloc.localization.chance import (
    chance_clique_size,
    chance_refined,
    near_miss_excess,
)
from lunarloc.localization.config import (
    LocalizationConfig,
    Mode,
    Registration,
    Solver,
    combined_sigma,
)
from lunarloc.localization.register import (
    _flattened,
    _handedness,
    _refine,
    _register,
    _register_robust,
    _residuals,
    rmse_limit,
)
from lunarloc.localization.provenance import OdometryBoundsOrigin, resolve_odometry_bounds
from lunarloc.localization.result import LocalizationResult, _nan_T
from lunarloc.localization.search import (
    _competitor_3d,
    _competitor_same_yaw,
    _search_3d,
    _search_yaw_bins,
)
from lunarloc.localization.uncertainty import (
    covariance_at_origin,
    distortion_allowance,
    distortion_covariance,
    error_at,
    pose_covariance,
    scale_check,
    shared_bias_covariance,
)
from lunarloc.localization.verify import Check, Evidence, verify

log = logging.getLogger(__name__)

__all__ = [
    "Mode",
    "Registration",
    "Solver",
    "LocalizationConfig",
    "LocalizationResult",
    "Check",
    "Evidence",
    "verify",
    "localize",
    "chance_clique_size",
]


def _check_map(m: LandmarkMap, name: str) -> np.ndarray:
    if not isinstance(m, LandmarkMap):
        raise InputError(f"{name} must be a LandmarkMap, got {type(m).__name__}")
    P = m.positions_xyz
    if len(P) == 0:
        raise InputError(f"{name} map is empty: no landmarks to localize with")
    if len(P) < 3:
        raise InputError(
            f"{name} map has {len(P)} landmark(s); at least 3 are needed to fix a pose"
        )
    spread = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if spread[0] < 1e-6:
        raise DegenerateGeometryError(f"{name} landmarks all coincide: the pose is undetermined")
    if spread[1] < 1e-6 * max(1.0, spread[0]) or spread[1] / spread[0] < 1e-4:
        raise DegenerateGeometryError(
            f"{name} landmarks are collinear: the rotation about their line is undetermined"
        )
    return P


def localize(
    reference: LandmarkMap,
    vehicle: LandmarkMap,
    config: LocalizationConfig | None = None,
    query_xyz: np.ndarray | None = None,
    path_xyz: np.ndarray | None = None,
) -> LocalizationResult:
    """Find ``T_ref_veh`` aligning `vehicle` to `reference`, or say why it can't be trusted.

    `query_xyz` (k, 3), vehicle frame: where the pose will be used (e.g. the rover's current
    position); the predicted error is judged there. Default: every vehicle landmark.
    `path_xyz` (F, 3), vehicle frame: the odometry path that built the vehicle map, to
    measure how far the rover travelled between the inliers and the query points (heading
    drift accumulates with it; see :func:`distortion_allowance`).

    Raises InputError / DegenerateGeometryError for unusable input (empty maps, fewer
    than 3 landmarks, coincident or collinear landmarks). A failed localization is not
    an error: it returns ``success=False`` with a reason.
    """
    # 1. the maps and the settings for them (a map without heights: 2D + yaw; the odometry bounds:
    # stated, else from the vehicle map's pose provenance, else the prior)
    reference, vehicle, cfg, bounds = _prepare(reference, vehicle, config)
    P = _Problem(reference, vehicle, cfg, timings={}, bounds=bounds)
    # 2. all-to-all putative associations, and the inliers chance alone would give
    P.associate()
    if P.num_associations == 0:
        return P.refused(
            "associations", 0, 1, ">=", "no putative associations (size pruning removed all)"
        )
    # 3. the densest consistent set (one sparse graph per yaw bin in gravity mode)
    screen = P.search()
    if screen is not None and not screen.passed:
        return P.refused(
            "screen", screen.score, screen.needed, ">=", _screen_reason(screen, cfg, P.required)
        )
    if len(P.best) < 3:
        return P.refused(
            "consistent_set",
            len(P.best),
            3,
            ">=",
            f"no consistent set of 3 or more associations (largest: {len(P.best)})",
        )
    # 4. Arun's SVD on the set, refinement, robust re-weighting
    why = P.register()
    if why is not None:
        return P.refused("registration", float("nan"), float("nan"), "<=", why, inliers=P.inl)
    # 5. the error budget where the pose is used: registration, odometry distortion, chance
    budget = P.error_budget(query_xyz, path_xyz)
    # 6. the competing hypothesis and the table of named checks
    return P.verify(budget, screen)


def _prepare(reference, vehicle, config):
    """The maps and the config localize() works with: a config of the right type, maps
    without heights (a rock catalogue from above) flattened to 2D + yaw, the per-map settings."""
    if config is not None:
        from lunarloc.core.validate import instance

        instance(config, "config", LocalizationConfig, "lunarloc.LocalizationConfig")
    # first call of a process: compile or load the kernels before any stage timer starts
    prepare_kernels()
    config, bounds = resolve_odometry_bounds(config or LocalizationConfig(), vehicle)
    if (
        isinstance(reference, LandmarkMap)
        and isinstance(vehicle, LandmarkMap)
        and not (reference.has_heights and vehicle.has_heights)
    ):
        # a map without heights (a rock catalogue from above): associate and register in
        # 2D + yaw; the pose's height, roll and pitch are not determined (left 0)
        reference, vehicle = _flattened(reference), _flattened(vehicle)
        config = replace(
            config or LocalizationConfig(), mode=Mode.GRAVITY, registration=Registration.YAW
        )
    _check_map(reference, "reference")
    _check_map(vehicle, "vehicle")
    return reference, vehicle, config.for_maps(reference, vehicle), bounds


def _screen_reason(screen, cfg, required: int) -> str:
    return (
        f"no consistent set large enough: the best of {screen.candidates} candidate poses voted by "
        f"the reference's rock triangles has {screen.score:.1f} inliers beyond chance "
        f"({screen.inliers} in all), under {cfg.screen.fraction:g} x the {required} acceptance "
        f"needs; the exhaustive search (~{screen.incidences:.2g} graph edges) was not run"
    )


@dataclass
class _Budget:
    """What :meth:`_Problem.error_budget` found at the query points."""

    query: np.ndarray
    C_c: np.ndarray
    centre_ref: np.ndarray
    pred_fit: np.ndarray
    pred: np.ndarray
    distortion: np.ndarray
    distortion_rot: np.ndarray
    pred_rot_deg: float
    bend: object
    k_chance: float
    near: int
    near_exp: float
    near_outer: float
    dscale: float
    scale_se: float


class _Problem:
    """One localize() call's state, step by step (each step one method)."""

    def __init__(
        self,
        reference: LandmarkMap,
        vehicle: LandmarkMap,
        cfg: LocalizationConfig,
        timings: dict,
        bounds: OdometryBoundsOrigin,
    ):
        self.reference, self.vehicle, self.cfg, self.timings = reference, vehicle, cfg, timings
        self.bounds = bounds  # where the odometry bounds in cfg came from
        self.Pr, self.Pv = reference.positions_xyz, vehicle.positions_xyz
        self.sigma_h, self.sigma_z = combined_sigma(reference, vehicle, cfg)
        # 0, 1 or 2 maps
        self.built_from_detections = sum(m.sightings is not None for m in (reference, vehicle))
        self.required, self.num_associations, self.num_edges = 0, 0, 0
        self.best, self.inl = [], np.zeros((0, 2), int)

    def base(self) -> dict:
        """The result fields every outcome after the association step carries."""
        return dict(
            required_inliers=self.required,
            num_associations=self.num_associations,
            num_edges=self.num_edges,
            timings=self.timings,
            odometry_bounds=self.bounds.to_dict(),
        )

    def refused(self, name, value, limit, op, why, inliers=None) -> LocalizationResult:
        """A result that says why not: one failed check, no pose."""
        fields = (
            self.base()
            if name != "associations"
            else dict(
                required_inliers=self.required,
                timings=self.timings,
                odometry_bounds=self.bounds.to_dict(),
            )
        )
        if name == "screen":
            fields.pop("num_edges")
        if name in ("consistent_set", "registration"):
            fields["clique_size"] = len(self.best)
        return LocalizationResult(
            False,
            _nan_T(),
            np.zeros((0, 2), int) if inliers is None else inliers,
            float("nan"),
            why,
            checks=[Check(name, value, limit, False, op, why)],
            **fields,
        )

    def associate(self) -> None:
        cfg, t0 = self.cfg, time.perf_counter()
        self.assoc, self.node_of = putative_associations(
            len(self.Pv),
            len(self.Pr),
            self.vehicle.sizes,
            self.reference.sizes,
            cfg.search.max_size_ratio,
        )
        self.num_associations = m = len(self.assoc)
        self.timings["associations"] = time.perf_counter() - t0
        self.chance = chance_clique_size(m, cfg.mode, cfg.search.epsilon_m, cfg.search.epsilon_z_m)
        self.required = max(
            cfg.acceptance.min_inliers, int(math.ceil(self.chance + cfg.acceptance.chance_margin))
        )

    def search(self):
        """The densest consistent set and its competitor; the screen's verdict (None: not run)."""
        cfg, t0 = self.cfg, time.perf_counter()
        if cfg.mode is Mode.GRAVITY:
            report: dict = {}
            self.best, self.competitor, self.best_yaw, self.num_edges = _search_yaw_bins(
                self.Pv, self.Pr, self.node_of, cfg, self.required, report
            )
        else:
            self.best, self.competitor, self.num_edges = _search_3d(
                self.Pv, self.Pr, self.node_of, self.assoc, cfg
            )
            self.best_yaw, report = None, {}
        screen = report.get("screen")
        if screen is not None:
            self.timings["screen"] = report["screen_s"]
            if not screen.passed:
                return screen
        self.timings["search"] = time.perf_counter() - t0 - self.timings.get("screen", 0.0)
        return screen

    def register(self) -> str | None:
        """T and the inliers (None), or why the set cannot be registered."""
        cfg, Pv, Pr = self.cfg, self.Pv, self.Pr
        self.t_register = time.perf_counter()
        self.inl = inl = self.assoc[self.best]
        try:
            T = _register(Pv[inl[:, 0]], Pr[inl[:, 1]], cfg)
        except DegenerateGeometryError as exc:
            self.timings["registration"] = time.perf_counter() - self.t_register
            return f"inliers are degenerate: {exc}"
        if cfg.refinement.enabled:
            T, inl = _refine(T, Pv, Pr, inl, cfg)
        try:
            T_w, w = (
                _register_robust(Pv[inl[:, 0]], Pr[inl[:, 1]], cfg, T)
                if cfg.refinement.enabled
                else (T, np.ones(len(inl)))
            )
            T = T_w
        except DegenerateGeometryError:
            w = np.ones(len(inl))
        self.T, self.inl, self.w = T, inl, w
        return None

    def error_budget(self, query_xyz, path_xyz) -> _Budget:
        """The predicted error at the query points: the registration's covariance, the
        odometry's distortion (stated bounds, or fitted from the maps with a prior), chance."""
        cfg, T, Pv, Pr, inl, w = self.cfg, self.T, self.Pv, self.Pr, self.inl, self.w
        query = Pv if query_xyz is None else as_points(query_xyz, "query points")
        C_c, centre_ref = pose_covariance(
            T, Pv[inl[:, 0]], Pr[inl[:, 1]], w, cfg.uncertainty.sigma_floor_m
        )
        # plus the error the inliers share and their residuals cannot show (CENTRE_BIAS_M): each map
        # built from detections (sightings given) brings its own centre bias, measured for two
        C_c = C_c + self.built_from_detections / 2 * shared_bias_covariance(
            cfg.uncertainty.centre_bias_m,
            cfg.uncertainty.centre_bias_yaw_deg,
            cfg.uncertainty.centre_bias_spread_m,
            transform_points(T, Pv[inl[:, 0]]),
            w,
        )
        pred_fit = error_at(C_c, centre_ref, T, query)
        path = None if path_xyz is None else as_points(path_xyz, "vehicle path")
        bend = None
        if cfg.odometry_bounds_stated:
            distortion, distortion_rot = distortion_allowance(
                query,
                Pv[inl[:, 0]],
                w,
                cfg.distortion.scale_error or 0.0,
                math.radians(cfg.distortion.heading_drift_deg_per_m or 0.0),
                path,
            )
        # no bounds stated: what the maps show of a bend or scale error, and how unsure that is
        else:
            distortion, distortion_rot = np.array([math.inf]), np.array([math.inf])
            if len(inl) >= cfg.distortion.fit_min_inliers:
                bend = self._fitted_bend(query, path)
        # the distortion is a bound (a bias), not a random error: added, not in quadrature
        pred = pred_fit + distortion
        rot_sigma = (
            math.sqrt(max(float(np.max(np.linalg.eigvalsh(C_c[3:, 3:]))), 0.0))
            if np.all(np.isfinite(C_c))
            else math.inf
        )
        pred_rot_deg = math.degrees(rot_sigma + float(distortion_rot.max()))
        if bend is not None:  # the registration counted once, with the bend's own uncertainty
            pred, pred_rot_deg = fitted_predicted_error(
                bend, cfg, pred_fit, math.degrees(rot_sigma)
            )
            distortion, distortion_rot = (
                pred - pred_fit,
                np.array([math.radians(pred_rot_deg) - rot_sigma]),
            )
        # the chance envelope was measured on consistent cores: refinement's chance additions
        # (more of them with a wider refinement radius) do not count towards beating it
        core = len(self.best)
        chance_gain = (
            chance_refined(T, Pv, Pr, self.assoc[self.best][:, 0], cfg.refinement.radius_m)
            if cfg.refinement.enabled
            else 0.0
        )
        k_chance = min(len(inl), core + max(0.0, len(inl) - core - chance_gain))
        near_outer = max(cfg.acceptance.near_miss_outer_m, 3 * cfg.refinement.radius_m)
        near, near_exp = near_miss_excess(T, Pv, Pr, inl[:, 0], cfg.refinement.radius_m, near_outer)
        dscale, scale_se = scale_check(
            T, Pv[inl[:, 0]], Pr[inl[:, 1]], w, cfg.uncertainty.sigma_floor_m
        )
        self.timings["registration"] = time.perf_counter() - self.t_register
        return _Budget(
            query,
            C_c,
            centre_ref,
            pred_fit,
            pred,
            distortion,
            distortion_rot,
            pred_rot_deg,
            bend,
            k_chance,
            near,
            near_exp,
            near_outer,
            dscale,
            scale_se,
        )

    def _fitted_bend(self, query, path):
        """The bend fitted from the maps alone, then with the odometry prior where the maps
        agree."""
        cfg, vehicle = self.cfg, self.vehicle
        arcs = (
            (vehicle.sighting_arc_m, vehicle.sighting_arc_min_m, vehicle.sighting_arc_max_m)
            if vehicle.has_sighting_arcs
            else None
        )
        fit_args = (
            self.T,
            self.Pv,
            self.Pr,
            self.inl,
            query,
            path,
            math.sqrt((2 * self.sigma_h**2 + self.sigma_z**2) / 3),
            cfg.refinement.radius_m,
            cfg.distortion.fit_rounds,
            arcs,
            cfg.distortion.max_sighting_span_m,
            cfg.distortion.fit_min_inliers,
        )
        bend = bending_fit(*fit_args)  # from the maps alone
        prior = (
            None
            if cfg.distortion.prior_drift_deg_per_m is None
            else math.radians(cfg.distortion.prior_drift_deg_per_m),
            cfg.distortion.prior_scale_error,
        )
        # the prior is per metre of the odometry's path: without the path (a straight stand-in)
        # there is no distance travelled for it to describe. It also narrowed a 6 m map against
        # a LAC grid below its quantisation's error (tests/test_sighting_arcs.py)
        if path is not None and any(v is not None for v in prior):
            conflict = prior_conflict(bend, *prior)
            if conflict <= PRIOR_CONFLICT_SIGMAS:
                bend = bending_fit(*fit_args, *prior)
                bend.prior = "applied"
            # the maps show a bend real odometry does not make: the prior does not describe them
            else:
                bend.prior = f"rejected: the maps' bend is {conflict:.1f} sigma from the prior"
        return bend

    def verify(self, b: _Budget, screen) -> LocalizationResult:
        """The competing hypothesis, the result, and the table of named checks deciding it."""
        cfg, T, Pv, Pr, inl = self.cfg, self.T, self.Pv, self.Pr, self.inl
        # competitor in 6-DoF mode: best set among associations the winner does not explain
        t0 = time.perf_counter()
        if cfg.mode is Mode.SIX_DOF:
            competitor = _competitor_3d(T, Pv, Pr, self.node_of, self.assoc, cfg)
        else:
            competitor = max(
                self.competitor,
                _competitor_same_yaw(
                    T, Pv, Pr, self.node_of, self.assoc, cfg, self.best_yaw, self.competitor
                ),
            )
        self.timings["verification"] = time.perf_counter() - t0

        res = _residuals(T, Pv[inl[:, 0]], Pr[inl[:, 1]])
        rmse = float(np.sqrt(np.mean(res**2)))
        R = T[:3, :3]
        out = LocalizationResult(
            False,
            T,
            inl,
            rmse,
            "",
            clique_size=len(self.best),
            competitor_size=int(competitor),
            predicted_error_m=float(b.pred.max()),
            scale_error=b.dscale,
            yaw_deg=math.degrees(yaw_of(R)),
            tilt_deg=math.degrees(tilt_angle(R)),
            distortion_error_m=float(b.distortion.max()),
            predicted_rotation_deg=b.pred_rot_deg,
            distortion_rotation_deg=math.degrees(float(b.distortion_rot.max())),
            near_misses=b.near,
            near_misses_expected=b.near_exp,
            covariance=covariance_at_origin(b.C_c, b.centre_ref)
            + distortion_covariance(
                transform_points(T, b.query[int(np.argmax(b.pred_fit + b.distortion))][None])[0],
                float(b.distortion.max()),
                float(b.distortion_rot.max()),
            ),
            distortion_fit={} if b.bend is None else asdict(b.bend),
            **self.base(),
        )
        Q = Pr[inl[:, 1]]
        s = np.linalg.svd(Q - Q.mean(axis=0), compute_uv=False) / math.sqrt(len(Q))
        k = len(inl)
        gravity = cfg.mode is Mode.GRAVITY
        ev = Evidence(
            inliers=k,
            rmse_m=rmse,
            rmse_limit_m=rmse_limit(cfg, self.sigma_h, self.sigma_z, k),
            sigma_h_m=self.sigma_h,
            sigma_z_m=self.sigma_z,
            extent_m=2 * s[0],
            planarity=s[1] / max(s[0], 1e-12),
            tilt_deg=out.tilt_deg if gravity else None,
            handedness=_handedness(Pv[inl[:, 0]], Q, np.random.default_rng(0)) if gravity else None,
            scale_error=b.dscale,
            scale_se=b.scale_se,
            near_misses=b.near,
            near_misses_expected=b.near_exp,
            near_inner_m=cfg.refinement.radius_m,
            near_outer_m=b.near_outer,
            predicted_error_m=float(b.pred.max()),
            distortion_error_m=float(b.distortion.max()),
            predicted_rotation_deg=b.pred_rot_deg,
            distortion_rotation_deg=math.degrees(float(b.distortion_rot.max())),
            inliers_beyond_chance=b.k_chance,
            required_inliers=self.required,
            chance_inliers=self.chance,
            num_associations=self.num_associations,
            competitor=int(competitor),
            distortion_fitted=b.bend is not None,
            odometry_bounds=self.bounds.text,
        )
        out.checks = verify(ev, cfg)
        if screen is not None:  # it passed: shown first, as a check that refuses nothing further
            out.checks.insert(
                0,
                Check(
                    "screen",
                    screen.score,
                    screen.needed,
                    True,
                    ">=",
                    "inliers beyond chance at the best pose voted by the reference's rock "
                    "triangles",
                ),
            )
        failed = [c for c in out.checks if not c.passed]
        out.success = not failed
        out.reason = failed[0].detail if failed else "ok"
        log.info("localize: %s (%d inliers, rmse %.3f m)", out.reason, k, rmse)
        return out


"""Edges (8 bytes each) of the built bins the search keeps for the same-yaw competitor
search, which needs the graphs of the bins around the winner again (13-15: 1.4 million
edges in all); beyond it the competitor rebuilds the bins it needs."""
"""Vehicle triangles the screen votes with at most: the vote's cost grows with them (a
150-landmark map at 15 cm: 6300 triangles, 117 000 matches, 0.3 s); the true pose keeps its
share of the votes in a sample."""


_WARM: bool | str = False


def warm_kernels(force: bool = False, jit: bool = False) -> float:
    """Compile (or load from the cache) every association kernel, in every mode and solver.
    Returns the seconds it took (0.0 once done in this process). Public as
    :func:`lunarloc.localization.warmup.warm_up`.

    Where the ahead-of-time kernels are built (:mod:`lunarloc.association.aot`) this only
    loads them; ``jit=True`` runs numba's JIT path even then, compiling into numba's cache
    (``lunarloc warm-up``: the fallback for argument types the build does not hold)."""
    global _WARM
    if _WARM in (("jit", True) if jit else ("jit", "aot", True)) and not force:
        return 0.0
    import contextlib

    from lunarloc.association.aot import exercising, jit_only
    from lunarloc.core.geometry import (
        euler_to_rotation,
        make_transform,
        transform_points,
    )

    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    # 80 x 40 = 3,200 associations: large enough for the search's per-bin bounds (their
    # kernels compile too), small enough to take a moment once compiled
    ref_xyz = np.c_[rng.uniform(-8, 8, (80, 2)), rng.normal(0, 0.2, 80)]
    T = make_transform(euler_to_rotation(0.0, 0.0, 0.7), np.array([3.0, -2.0, 0.1]))
    veh_xyz = transform_points(np.linalg.inv(T), ref_xyz[:40]) + rng.normal(0, 0.005, (40, 3))
    ref, veh = LandmarkMap(ref_xyz, frame="ref"), LandmarkMap(veh_xyz, frame="veh")
    with exercising(), jit_only() if jit else contextlib.nullcontext():
        for mode in Mode:
            for solver in Solver:
                localize(ref, veh, LocalizationConfig(mode=mode, solver=solver))
    _WARM = "jit" if jit else (_WARM or "aot")
    return time.perf_counter() - t0


def prepare_kernels():
    """Once a process: the kernels ready before any stage timer starts (loaded ahead of time,
    from numba's cache, or compiled, announced on the log); see
    :func:`lunarloc.association.aot.prepare_kernels`."""
    from lunarloc.association.aot import prepare_kernels as prepare

    return prepare(warm_kernels)
