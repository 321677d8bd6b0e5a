"""Is a claimed pose right, and is its stated uncertainty honest? Families of maps the
localizer never saw, run through the full, indexed and automatic searches, with the
command line's default configuration (no odometry bounds stated: the bend fit with the
odometry prior for the synthetic maps, which state no pose provenance; for the real families the
bounds the vehicle file's pose provenance gives, :data:`REAL_CONFIGS`) and with the maps stated
rigid.

Each case is a reference map, a vehicle map in a random frame (any yaw, a small tilt,
up to 100 m away) with the true ``T_ref_veh`` (none for a wrong site), and the point
where the pose is used (the vehicle map's centre, or the rover's last position). For
every (family, configuration, search) it counts the cases, the poses claimed
(``success``), the claims that are right (within 10 cm and 1 degree at the query point),
the confident-wrong ones (claimed but not right: must be 0) and the normalised estimation
error squared of the claims (NEES: the position error at the query point, squared
Mahalanobis distance under the result's covariance carried there, 3 degrees of freedom):
the share under 3.53 (the 68.3 % quantile) and under 14.16 (99.73 %). A calibrated
uncertainty puts 60-80 % and at least 99 % there.

Families (synthetic, seeded; each case draws its parameters from the stated range):

* ``outliers uniform``: +50-100 % false rocks spread over the window;
* ``outliers clustered``: +50-100 % false rocks 0.3-1 m from true ones;
* ``drops``: 30-60 % of the rocks not detected;
* ``overlap``: only 10-40 % of the vehicle map's rocks lie in the reference;
* ``tilt``: the vehicle map tilted by 1-5 degrees (the mode allows 1.5);
* ``noise unstated`` / ``noise stated``: 3-10 cm landmark noise, the vehicle map stating it
  (``sigma_xy_m``) or not;
* ``quantisation``: the reference on a 15 cm grid (stating cell / sqrt(12));
* ``wrong site``: the vehicle map from another field (no true pose: any claim is wrong);
* ``lattice``: a jittered lattice, 2 m spacing, 2-3 cm jitter, 676 or 2,116 rocks;
* ``motifs``: one 8-rock motif repeated on a 5 m grid;
* ``copied map``: a 150-rock field copied five times side by side.

:func:`run_cases` runs them; :func:`summarise` gives the table; ``benchmarks/calibration.py``
prints it and ``tests/test_calibration.py`` runs a fast subset that fails on any
confident-wrong pose.
"""

from __future__ import annotations

import logging
import math
import zlib
from dataclasses import asdict, dataclass, field
from typing import Callable, Iterable

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.core.errors import LunarLocError
from lunarloc.core.geometry import (
    euler_to_rotation,
    invert_transform,
    make_transform,
    rotation_angle,
    transform_points,
)
from lunarloc.io.maps import POSE_COLUMN, LandmarkMap, PoseProvenance
from lunarloc.localization.large import localize_large
from lunarloc.localization.config import DistortionConfig, LocalizationConfig
from lunarloc.sim.fields import uniform_rock_field

log = logging.getLogger(__name__)

__all__ = [
    "Case",
    "Outcome",
    "CONFIGS",
    "SEARCHES",
    "FAMILIES",
    "REAL_FAMILIES",
    "REAL_CONFIGS",
    "REAL_EXTRA_CONFIGS",
    "make_cases",
    "run_case",
    "run_cases",
    "run_real",
    "summarise",
    "nees_at",
    "NEES_68",
    "NEES_997",
    "RIGHT_M",
    "RIGHT_DEG",
]

RIGHT_M = 0.10  # a claimed pose is right within this at the query point ...
RIGHT_DEG = 1.0  # ... and this in rotation
NEES_68 = 3.5267  # chi-square, 3 dof: 68.27 % quantile
NEES_997 = 14.156  # 99.73 % quantile

#: configurations: the command line's default (no odometry bounds: the bend fit with the prior)
#: and the maps stated rigid (as ``lunarloc bench pairs`` states them)
CONFIGS: dict[str, Callable[[], LocalizationConfig]] = {
    "cli default": LocalizationConfig,
    "stated rigid": lambda: LocalizationConfig(
        distortion=DistortionConfig(scale_error=0.0, heading_drift_deg_per_m=0.0)
    ),
}
SEARCHES = ("full", "indexed", "auto")


@dataclass
class Case:
    """One localization problem with its truth. ``T_ref_veh`` is all NaN when the vehicle map
    is not in the reference (a wrong site: only a refusal is right)."""

    family: str
    seed: int
    reference: LandmarkMap
    vehicle: LandmarkMap
    T_ref_veh: np.ndarray
    query_xyz: np.ndarray  # (1, 3) vehicle frame: where the pose is used
    path_xyz: np.ndarray | None = None
    params: dict = field(default_factory=dict)


@dataclass
class Outcome:
    """What one case gave under one configuration and search."""

    family: str
    seed: int
    config: str
    search: str
    claimed: bool
    right: bool
    err_m: float
    rot_err_deg: float
    predicted_error_m: float
    nees: float
    reason: str
    time_s: float
    params: dict = field(default_factory=dict)

    @property
    def confident_wrong(self) -> bool:
        return self.claimed and not self.right

    def to_dict(self) -> dict:
        return {**asdict(self), "confident_wrong": self.confident_wrong}


# --------------------------------------------------------------------------- building cases


def _random_frame(
    rng: np.random.Generator, tilt_deg: float | None = None, max_tilt_deg: float = 0.5
) -> np.ndarray:
    """A random T_veh_ref: any yaw, a tilt (exactly `tilt_deg` when given), up to 100 m away."""
    if tilt_deg is None:
        roll, pitch = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    else:
        a = rng.uniform(0, 2 * math.pi)
        roll, pitch = math.radians(tilt_deg) * math.cos(a), math.radians(tilt_deg) * math.sin(a)
    return make_transform(
        euler_to_rotation(roll, pitch, rng.uniform(-math.pi, math.pi)), rng.uniform(-100, 100, 3)
    )


def _window(
    rng: np.random.Generator, P: np.ndarray, n_true: int, detect_prob: float = 0.85
) -> np.ndarray:
    """Indices of `n_true` rocks of P near a random rock, each detected with `detect_prob`."""
    centre = P[rng.integers(len(P)), :2]
    k = min(len(P), int(math.ceil(n_true / detect_prob)) + 1)
    near = np.asarray(cKDTree(P[:, :2]).query(centre, k=k)[1])
    seen = near[rng.random(len(near)) < detect_prob][:n_true]
    if len(seen) < 3:
        seen = near[: max(3, n_true)]
    return seen


def _case(
    family: str,
    seed: int,
    rng: np.random.Generator,
    reference: LandmarkMap,
    world_xyz: np.ndarray,
    true: bool = True,
    tilt_deg: float | None = None,
    sigma_m: float | None = None,
    **params,
) -> Case:
    """The vehicle map of `world_xyz` (reference frame) in a random frame; its query point is
    the map's centre."""
    T_veh_ref = _random_frame(rng, tilt_deg)
    world = world_xyz[rng.permutation(len(world_xyz))]
    veh_xyz = transform_points(T_veh_ref, world)
    sig = None if sigma_m is None else np.full(len(veh_xyz), sigma_m)
    vehicle = LandmarkMap(veh_xyz, frame="vehicle", sigma_xy_m=sig, sigma_z_m=sig)
    query = veh_xyz.mean(axis=0)[None]
    T = invert_transform(T_veh_ref) if true else np.full((4, 4), np.nan)
    return Case(family, seed, reference, vehicle, T, query, None, params)


def _field(rng, n=400) -> LandmarkMap:
    return uniform_rock_field(rng, n)


def _lattice(rng: np.random.Generator, side: int, spacing_m: float, jitter_m: float) -> LandmarkMap:
    g = np.arange(side) * spacing_m
    X, Y = np.meshgrid(g, g)
    xy = np.c_[X.ravel(), Y.ravel()] + rng.normal(0, jitter_m, (side * side, 2))
    return LandmarkMap(np.c_[xy, rng.normal(0, jitter_m, side * side)], frame="lattice")


def _build(family: str, seed: int) -> Case:
    rng = np.random.default_rng([zlib.crc32(family.encode()), seed])
    noise = 0.01
    if family in ("outliers uniform", "outliers clustered"):
        ref = _field(rng)
        P = ref.positions_xyz
        seen = _window(rng, P, int(rng.integers(30, 70)))
        true = P[seen] + rng.normal(0, noise, (len(seen), 3))
        r = rng.uniform(0.5, 1.0)
        n_out = int(round(r * len(seen)))
        if family == "outliers uniform":
            lo, hi = true[:, :2].min(axis=0), true[:, :2].max(axis=0)
            out = np.c_[rng.uniform(lo, hi, (n_out, 2)), rng.normal(true[:, 2].mean(), 0.1, n_out)]
        else:
            base = true[rng.integers(len(true), size=n_out)]
            a = rng.uniform(0, 2 * math.pi, n_out)
            d = rng.uniform(0.3, 1.0, n_out)
            out = base + np.c_[d * np.cos(a), d * np.sin(a), rng.normal(0, 0.05, n_out)]
        return _case(family, seed, rng, ref, np.vstack([true, out]), false_share=round(r, 2))
    if family == "drops":
        ref = _field(rng)
        p = rng.uniform(0.4, 0.7)
        seen = _window(rng, ref.positions_xyz, int(rng.integers(25, 60)), detect_prob=p)
        return _case(
            family,
            seed,
            rng,
            ref,
            ref.positions_xyz[seen] + rng.normal(0, noise, (len(seen), 3)),
            detected=round(p, 2),
        )
    if family == "overlap":
        full = _field(rng, 600)
        P = full.positions_xyz
        seen = _window(rng, P, 60)
        share = rng.uniform(0.1, 0.4)
        # the reference stops at a line across the window, leaving `share` of its rocks inside
        a = rng.uniform(0, 2 * math.pi)
        u = np.array([math.cos(a), math.sin(a)])
        cut = np.quantile(P[seen, :2] @ u, 1 - share)
        ref = LandmarkMap(P[P[:, :2] @ u >= cut], frame="site")
        return _case(
            family,
            seed,
            rng,
            ref,
            P[seen] + rng.normal(0, noise, (len(seen), 3)),
            overlap=round(share, 2),
        )
    if family == "tilt":
        ref = _field(rng)
        tilt = rng.uniform(1.0, 5.0)
        seen = _window(rng, ref.positions_xyz, int(rng.integers(30, 70)))
        return _case(
            family,
            seed,
            rng,
            ref,
            ref.positions_xyz[seen] + rng.normal(0, noise, (len(seen), 3)),
            tilt_deg=tilt,
            tilt=round(tilt, 2),
        )
    if family in ("noise unstated", "noise stated"):
        ref = _field(rng)
        s = rng.uniform(0.03, 0.10)
        seen = _window(rng, ref.positions_xyz, int(rng.integers(40, 80)))
        return _case(
            family,
            seed,
            rng,
            ref,
            ref.positions_xyz[seen] + rng.normal(0, s, (len(seen), 3)),
            sigma_m=s if family == "noise stated" else None,
            noise_m=round(s, 3),
        )
    if family == "quantisation":
        field_ = _field(rng)
        P = field_.positions_xyz
        cell = 0.15
        Q = np.c_[(np.floor(P[:, :2] / cell) + 0.5) * cell, P[:, 2]]
        sig = np.full(len(Q), cell / math.sqrt(12))
        ref = LandmarkMap(Q, frame="grid", sigma_xy_m=sig, sigma_z_m=np.full(len(Q), 0.02))
        seen = _window(rng, P, int(rng.integers(30, 70)))
        return _case(
            family, seed, rng, ref, P[seen] + rng.normal(0, noise, (len(seen), 3)), cell_m=cell
        )
    if family == "wrong site":
        ref = _field(rng)
        other = _field(rng)
        seen = _window(rng, other.positions_xyz, int(rng.integers(30, 80)))
        return _case(
            family,
            seed,
            rng,
            ref,
            other.positions_xyz[seen] + rng.normal(0, noise, (len(seen), 3)),
            true=False,
        )
    if family == "lattice":
        side = (26, 46)[seed % 2]
        jit = rng.uniform(0.02, 0.03)
        ref = _lattice(rng, side, 2.0, jit)
        seen = _window(rng, ref.positions_xyz, int(rng.integers(25, 70)))
        true = ref.positions_xyz[seen] + rng.normal(0, noise, (len(seen), 3))
        n_out = len(seen) // 10
        lo, hi = true[:, :2].min(axis=0), true[:, :2].max(axis=0)
        out = np.c_[rng.uniform(lo, hi, (n_out, 2)), rng.normal(0, jit, n_out)]
        return _case(
            family,
            seed,
            rng,
            ref,
            np.vstack([true, out]),
            rocks=side * side,
            jitter_m=round(jit, 3),
        )
    if family == "motifs":
        motif = np.c_[rng.uniform(0, 3, (8, 2)), rng.normal(0, 0.05, 8)]
        nx = 8
        offs = np.array([(i * 5.0, j * 5.0, 0.0) for i in range(nx) for j in range(nx)])
        P = (offs[:, None, :] + motif[None]).reshape(-1, 3) + rng.normal(
            0, 0.005, (len(offs) * 8, 3)
        )
        ref = LandmarkMap(P, frame="motifs")
        seen = _window(rng, P, int(rng.integers(20, 40)))
        return _case(
            family, seed, rng, ref, P[seen] + rng.normal(0, noise, (len(seen), 3)), rocks=len(P)
        )
    if family == "copied map":
        patch = _field(rng, 150).positions_xyz
        w = float(np.ptp(patch[:, 0])) + 2.0
        P = np.vstack([patch + np.array([k * w, 0.0, 0.0]) for k in range(5)])
        ref = LandmarkMap(P, frame="copies")
        seen = _window(rng, P, int(rng.integers(30, 60)))
        return _case(
            family, seed, rng, ref, P[seen] + rng.normal(0, noise, (len(seen), 3)), copies=5
        )
    raise ValueError(f"unknown family {family!r}")


FAMILIES = (
    "outliers uniform",
    "outliers clustered",
    "drops",
    "overlap",
    "tilt",
    "noise unstated",
    "noise stated",
    "quantisation",
    "wrong site",
    "lattice",
    "motifs",
    "copied map",
)


def make_cases(
    families: Iterable[str] = FAMILIES, per_family: int = 10, first_seed: int = 0
) -> list[Case]:
    """`per_family` seeded cases of each family."""
    return [_build(f, s) for f in families for s in range(first_seed, first_seed + per_family)]


# --------------------------------------------------------------------------- judging


def nees_at(
    T_est: np.ndarray, T_true: np.ndarray, covariance: np.ndarray, point_veh: np.ndarray
) -> float:
    """Normalised estimation error squared of the position of a vehicle-frame point: the
    estimated position's error in the reference frame, squared Mahalanobis distance under
    the result's covariance carried to that point (``T_true = exp(xi) T_est``, the error of
    a reference point p is ``-(rho + phi x p)``: covariance ``A C A^T``, ``A = [I, -[p]x]``).
    NaN when the covariance is not finite or singular there."""
    C = np.asarray(covariance, float)
    if not np.all(np.isfinite(C)):
        return math.nan
    p_est = transform_points(T_est, np.asarray(point_veh, float).reshape(1, 3))[0]
    p_true = transform_points(T_true, np.asarray(point_veh, float).reshape(1, 3))[0]
    x, y, z = p_est
    A = np.hstack([np.eye(3), -np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])])
    S = A @ C @ A.T
    e = p_est - p_true
    try:
        return float(e @ np.linalg.solve(S, e))
    except np.linalg.LinAlgError:
        return math.nan


def run_case(
    case: Case,
    config: str = "cli default",
    search: str = "auto",
    loc_config: LocalizationConfig | None = None,
) -> Outcome:
    """Localize one case and judge it (a refusal is never wrong; an input error is a refusal)."""
    import time

    cfg = loc_config if loc_config is not None else CONFIGS[config]()
    t0 = time.perf_counter()
    try:
        res = localize_large(
            case.reference,
            case.vehicle,
            cfg,
            search=search,
            query_xyz=case.query_xyz,
            path_xyz=case.path_xyz,
        )
    except LunarLocError as exc:
        return Outcome(
            case.family,
            case.seed,
            config,
            search,
            False,
            False,
            math.nan,
            math.nan,
            math.nan,
            math.nan,
            f"input refused: {exc}",
            time.perf_counter() - t0,
            case.params,
        )
    dt = time.perf_counter() - t0
    err = rot = nees = math.nan
    known = bool(np.all(np.isfinite(case.T_ref_veh)))
    if known and np.all(np.isfinite(res.T_ref_veh)):
        q = case.query_xyz.reshape(1, 3)
        err = float(
            np.linalg.norm(transform_points(res.T_ref_veh, q) - transform_points(case.T_ref_veh, q))
        )
        rot = math.degrees(rotation_angle(res.T_ref_veh[:3, :3] @ case.T_ref_veh[:3, :3].T))
        nees = nees_at(res.T_ref_veh, case.T_ref_veh, res.covariance, q[0])
    right = bool(known and err < RIGHT_M and rot < RIGHT_DEG)
    return Outcome(
        case.family,
        case.seed,
        config,
        search,
        bool(res.success),
        right,
        err,
        rot,
        float(res.predicted_error_m),
        nees,
        res.reason,
        dt,
        case.params,
    )


def run_cases(
    cases: Iterable[Case],
    configs: Iterable[str] = tuple(CONFIGS),
    searches: Iterable[str] = SEARCHES,
    progress: Callable[[Outcome], None] | None = None,
) -> list[Outcome]:
    out = []
    for case in cases:
        for c in configs:
            for s in searches:
                o = run_case(case, c, s)
                out.append(o)
                if progress:
                    progress(o)
    return out


def summarise(outcomes: Iterable[Outcome]) -> list[dict]:
    """One row per (family, config, search): cases, claimed, right and claimed,
    confident-wrong, and the NEES shares of the claims (under 3.53 and 14.16; None without
    claims)."""
    groups: dict[tuple, list[Outcome]] = {}
    for o in outcomes:
        groups.setdefault((o.family, o.config, o.search), []).append(o)
    rows = []
    for (fam, cfg, search), g in groups.items():
        claims = [o for o in g if o.claimed]
        nees = np.array([o.nees for o in claims if math.isfinite(o.nees)])
        rows.append(
            {
                "family": fam,
                "config": cfg,
                "search": search,
                "cases": len(g),
                "claimed": len(claims),
                "right": sum(o.right for o in claims),
                "confident_wrong": sum(o.confident_wrong for o in g),
                "nees_n": int(len(nees)),
                "nees_68": float(np.mean(nees <= NEES_68)) if len(nees) else None,
                "nees_997": float(np.mean(nees <= NEES_997)) if len(nees) else None,
            }
        )
    return rows


def format_table(rows: list[dict]) -> str:
    """Markdown table of :func:`summarise`'s rows."""
    lines = [
        "| family | config | search | cases | claimed | right | confident-wrong | NEES < 3.53 | "
        "NEES < 14.16 |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]

    def pct(v):
        return "-" if v is None else f"{v:.0%}"

    for r in rows:
        lines.append(
            f"| {r['family']} | {r['config']} | {r['search']} | {r['cases']} | {r['claimed']} | "
            f"{r['right']} | {r['confident_wrong']} | {pct(r['nees_68'])} | {pct(r['nees_997'])} |"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------- real traverses

#: Families on the 17 real LunarLoc traverses: every pair (reference, vehicle) with the vehicle map
#: in a random frame (seed 0, as ``lunarloc bench pairs``), built by the odometry distortion named
#: (``heading drift deg/m, scale error, window m, scale about the centroid``; none: the
#: traverse's ground-truth poses), judged at the rover's last position (the query; the path given).
REAL_FAMILIES: dict[str, tuple[float, float, float | None, float]] = {
    "real pairs": (0.0, 0.0, None, 1.0),
    "real scale +0.5%": (0.0, 0.0, None, 1.005),
    "real scale +1%": (0.0, 0.0, None, 1.01),
    "real drift 0.025 deg/m 60 m": (0.025, 0.0, 60.0, 1.0),
    "real drift 0.05 deg/m 30 m": (0.05, 0.0, 30.0, 1.0),
    "real drift 0.1 deg/m 30 m": (0.1, 0.0, 30.0, 1.0),
    "real drift 0.05 deg/m +1% 60 m": (0.05, 0.01, 60.0, 1.0),
}

#: configurations of the real families: the CLI's default, and the odometry's bounds stated as
#: they are (0 for the ground-truth-posed maps: what ``lunarloc bench pairs`` states).
#: "cli default" is what ``lunarloc localize REF VEH`` does with the file that holds the vehicle
#: map: no bounds stated, the map's pose provenance as :func:`lunarloc.io.maps.load_vehicle` reads
#: it from that file (tests/test_provenance.py): for the ground-truth-posed maps a traverse CSV in
#: the dataset's schema (rigid), for the distorted ones a traverse CSV that lunarloc wrote from
#: odometry poses (``pose`` column ``odometry``: the prior). Two more can be asked for by name:
#: "no provenance" (a map whose file says nothing, e.g. another tool's landmark CSV: the prior) and
#: "claimed rigid" (every map's file says ground truth, the distorted ones falsely).
REAL_CONFIGS = ("cli default", "stated bounds")
REAL_EXTRA_CONFIGS = ("no provenance", "claimed rigid")


def _real_config(
    config: str, drift: float, scale_error: float, scale: float
) -> tuple[LocalizationConfig, PoseProvenance | None]:
    """The configuration and the vehicle map's pose provenance of one real-family run."""
    from lunarloc.io.maps import DATASET_PROVENANCE, POSE_GROUND_TRUTH, POSE_ODOMETRY

    ground_truth = drift == 0 and scale_error == 0 and scale == 1.0
    if config == "cli default":
        return LocalizationConfig(), (
            DATASET_PROVENANCE
            if ground_truth
            else PoseProvenance(POSE_ODOMETRY, "", f"the file's {POSE_COLUMN} column")
        )
    if config == "stated bounds":
        return LocalizationConfig(
            distortion=DistortionConfig(
                scale_error=max(abs(scale_error), abs(scale - 1.0)),
                heading_drift_deg_per_m=abs(drift),
            )
        ), None
    if config == "no provenance":
        return LocalizationConfig(), None
    if config == "claimed rigid":
        return LocalizationConfig(), PoseProvenance(
            POSE_GROUND_TRUTH, "", f"the file's {POSE_COLUMN} column"
        )
    raise ValueError(
        f"unknown configuration {config!r} (one of {REAL_CONFIGS + REAL_EXTRA_CONFIGS})"
    )


def run_real(
    data_dir,
    families: Iterable[str] = ("real pairs",),
    configs: Iterable[str] = REAL_CONFIGS,
    pairs: Iterable[tuple[int, int]] | None = None,
    progress: Callable[[Outcome], None] | None = None,
    cache: dict | None = None,
) -> list[Outcome]:
    """Localize every pair of every real family under every configuration and judge it at the
    rover (right: within :data:`RIGHT_M` and :data:`RIGHT_DEG`; NEES of the rover's position under
    the result's covariance carried there). ``Outcome.seed`` is ``100 * reference + vehicle``.
    `cache`: a dict that keeps the loaded traverses and reference maps between calls."""
    import itertools
    import time

    from lunarloc.localization.localize import localize
    from lunarloc.pipeline.evaluation import (
        DriftModel,
        aggregate_detections,
        find_traverses,
        load_traverse,
        vehicle_map,
    )

    paths = find_traverses(data_dir)
    pairs = list(itertools.combinations(sorted(paths), 2)) if pairs is None else list(pairs)
    cache = {} if cache is None else cache
    travs: dict = cache.setdefault("traverses", {})
    refs: dict = cache.setdefault("references", {})
    out = []
    for fam in families:
        drift, scale_error, window, scale = REAL_FAMILIES[fam]
        model = DriftModel(drift, scale_error)
        for a, b in pairs:
            for k in (a, b):
                if k not in travs:
                    travs[k] = load_traverse(paths[k])
            if a not in refs:
                refs[a] = aggregate_detections(
                    travs[a].detections_xyz, travs[a].detection_frame, None, frame=travs[a].name
                )
            veh, T_true, last_v, path_v = vehicle_map(
                travs[b], np.random.default_rng([0, a, b]), None, model, window, scale
            )
            for config in configs:
                cfg, provenance = _real_config(config, drift, scale_error, scale)
                veh.pose_provenance = provenance
                t0 = time.perf_counter()
                res = localize(refs[a], veh, cfg, query_xyz=last_v[None], path_xyz=path_v)
                dt = time.perf_counter() - t0
                err = rot = nees = math.nan
                if np.all(np.isfinite(res.T_ref_veh)):
                    err = float(
                        np.linalg.norm(
                            transform_points(res.T_ref_veh, last_v[None])[0]
                            - transform_points(T_true, last_v[None])[0]
                        )
                    )
                    E = res.T_ref_veh @ invert_transform(T_true)
                    rot = math.degrees(rotation_angle(E[:3, :3]))
                    nees = nees_at(res.T_ref_veh, T_true, res.covariance, last_v)
                right = bool(err < RIGHT_M and rot < RIGHT_DEG)
                o = Outcome(
                    fam,
                    100 * a + b,
                    config,
                    "full",
                    bool(res.success),
                    right,
                    err,
                    rot,
                    float(res.predicted_error_m),
                    nees,
                    res.reason,
                    dt,
                    {"pair": f"{a}-{b}"},
                )
                out.append(o)
                if progress:
                    progress(o)
    return out
