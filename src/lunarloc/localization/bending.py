"""The vehicle map's odometry bend: fitted from the two maps, regularised by a prior of real
odometry."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.core.geometry import (
    exp_so3,
    make_transform,
    transform_points,
    yaw_of,
)
from lunarloc.io.maps import path_arc_length_m
from lunarloc.localization.config import LocalizationConfig

log = logging.getLogger(__name__)


@dataclass
class BendFit:
    """A non-rigid model of the vehicle map fitted to its inliers (:func:`bending_fit`): the
    odometry that built it drifted in heading by ``drift_rad_per_m`` per metre travelled and
    mis-scaled its path by ``scale_error``, each with its standard error.

    ``shift_m`` : largest distance, over the query points, between where the rigid fit and the
        bent model put them (what the rigid pose gets wrong if the map is bent as fitted);
    ``sigma_m`` : largest 1-sigma position uncertainty of the bent model there beyond the rigid
        model's (how well the data fix the bending as seen from the query points: large when the
        inliers cover little of the path; the rigid pose's own uncertainty is the registration's,
        counted once in the predicted error, :func:`fitted_predicted_error`);
    ``rotation_shift_deg`` / ``rotation_sigma_deg`` : the same for the heading at the query points;
    ``chi2_drop`` : decrease of the inliers' chi-square from the rigid fit to the bent model
        (2 extra parameters: above ~13.8 the bend is real at 0.999 confidence);
    ``inliers`` : inlier pairs the bent model is fitted to; ``path_given`` : False when the path
        was not given and a straight path along the map's principal axis stood in for it;
    ``placement`` : where each landmark was placed along the path: ``"sightings"`` (the map's
        sighting arcs), ``"nearest path point"`` or ``"straight stand-in"``;
    ``left_out`` : inliers left out of the fit because where they were seen from is not known
        well enough (a path that passed them more than once);
    ``floor_sigma_m`` / ``rotation_floor_sigma_deg`` : largest 1-sigma effect at the query points
        of the apparent drift and scale of real maps (``DRIFT_FLOOR_DEG_PER_M``, ``SCALE_FLOOR``)
        that the fit's standard errors do not hold, with the rigid part re-fitted."""

    drift_rad_per_m: float
    drift_se: float
    scale_error: float
    scale_se: float
    shift_m: float
    sigma_m: float
    rotation_shift_deg: float
    rotation_sigma_deg: float
    chi2_drop: float
    inliers: int
    path_given: bool
    placement: str = "straight stand-in"
    left_out: int = 0
    floor_sigma_m: float = 0.0
    rotation_floor_sigma_deg: float = 0.0
    prior: str = (
        "none"  # the odometry prior: "applied", "rejected: ..." (prior-data conflict) or "none"
    )


def _straight_path(points_xyz: np.ndarray, step_m: float = 0.25) -> np.ndarray:
    """A stand-in odometry path: a straight line along the horizontal principal axis of the
    points, over their extent (a traverse that drove straight through its map)."""
    P = np.asarray(points_xyz, float)
    c = P.mean(axis=0)
    _, _, Vt = np.linalg.svd(P[:, :2] - c[:2], full_matrices=False)
    a = np.r_[Vt[0], 0.0]
    u = (P - c) @ a
    t = np.arange(u.min(), u.max() + step_m, step_m)
    return c + t[:, None] * a


class _Unbender:
    """Undo a heading drift ``delta`` (rad per metre travelled) and a path scale error
    ``kappa`` in vehicle-frame points, each placed at its nearest (horizontally) point of the
    odometry path: the path is re-integrated with every step turned back by -delta * s (s its
    distance travelled) and shrunk by 1 / (1 + kappa); a point keeps its offset from its path
    point (a stereo measurement, not odometry), turned back with it."""

    def __init__(self, path_xyz: np.ndarray, spacing_m: float = 0.25):
        path = np.asarray(path_xyz, float)
        arc = path_arc_length_m(path)
        keep = np.unique(
            np.r_[np.searchsorted(arc, np.arange(0.0, arc[-1], spacing_m)), len(path) - 1]
        )
        self.path = path[
            keep
        ]  # one point every spacing_m: the model's cost does not grow with the frame rate
        self.arc = arc[
            keep
        ]  # the given path's own arc length at the kept points (where sightings are stated)
        self.steps = np.diff(self.path, axis=0)
        self.s = np.r_[0.0, np.cumsum(np.linalg.norm(self.steps[:, :2], axis=1))]
        self.tree = cKDTree(self.path[:, :2])
        self._last = None

    def index(self, points_xyz: np.ndarray) -> np.ndarray:
        """Each point's nearest (horizontally) path point: the stand-in for where it was seen
        from."""
        return self.tree.query(np.asarray(points_xyz, float)[:, :2])[1]

    def index_at_arc(self, arc_m: np.ndarray) -> np.ndarray:
        """The path point at each arc length (m from the path's first pose)."""
        a = np.clip(np.asarray(arc_m, float), 0.0, self.arc[-1])
        j = np.clip(np.searchsorted(self.arc, a), 1, max(len(self.arc) - 1, 1))
        return (
            np.where(np.abs(self.arc[j - 1] - a) <= np.abs(self.arc[j] - a), j - 1, j)
            if len(self.arc) > 1
            else np.zeros(len(a), int)
        )

    def passes(self, points_xyz: np.ndarray, range_m: float, margin_m: float) -> np.ndarray:
        """How many separate passes of the path come within sight of each point: path points
        within `range_m` (or `margin_m` beyond its nearest one, when farther) whose arc lengths
        form runs broken by gaps of more than 1 m. Without sighting arcs a landmark passed more
        than once may have been seen from any of the passes, and its nearest point may be the
        wrong one."""
        P = np.asarray(points_xyz, float)[:, :2]
        d = self.tree.query(P)[0]
        out = np.zeros(len(P), int)
        for i, near in enumerate(self.tree.query_ball_point(P, np.maximum(range_m, d + margin_m))):
            a = np.sort(self.arc[near])
            out[i] = 1 + int(np.count_nonzero(np.diff(a) > 1.0)) if len(a) else 0
        return out

    def _bent_path(self, delta: float, kappa: float) -> np.ndarray:
        # the last one is kept: a finite-difference Jacobian varies one parameter at a time,
        # so most of its calls share (delta, kappa) and the re-integration
        if self._last is None or self._last[0] != (delta, kappa):
            a = -delta * self.s[1:]
            c, sn = np.cos(a), np.sin(a)
            st = self.steps
            turned = np.stack(
                [c * st[:, 0] - sn * st[:, 1], sn * st[:, 0] + c * st[:, 1], st[:, 2]], axis=1
            )
            path = self.path[0] + np.vstack(
                [np.zeros((1, 3)), np.cumsum(turned / (1.0 + kappa), axis=0)]
            )
            self._last = ((delta, kappa), path)
        return self._last[1]

    def __call__(
        self, points_xyz: np.ndarray, idx: np.ndarray, delta: float, kappa: float
    ) -> np.ndarray:
        path = self._bent_path(float(delta), float(kappa))
        rel = np.asarray(points_xyz, float) - self.path[idx]
        b = -delta * self.s[idx]
        cb, sb = np.cos(b), np.sin(b)
        return path[idx] + np.stack(
            [cb * rel[:, 0] - sb * rel[:, 1], sb * rel[:, 0] + cb * rel[:, 1], rel[:, 2]], axis=1
        )

    def heading(self, idx: np.ndarray, delta: float) -> np.ndarray:
        """Heading correction (rad) the model applies at path points `idx`."""
        return -delta * self.s[idx]


#: without sighting arcs a landmark may have been seen from any path point within this range
#: (the LunarLoc traverses: 99.9 % of detections within 5.9 m of the rover, all within 6.2 m),
#: or this margin beyond its nearest path point when that is farther
SIGHTING_RANGE_M = 6.0
PASS_MARGIN_M = 2.0
#: a query point this close to the path's last pose is the rover there (not an earlier pass)
QUERY_AT_END_M = 0.05
#: Apparent distortion of real maps that the bend model's own standard errors do not hold,
#: added in quadrature to them: heading drift (deg/m) and scale error. Measured on the 136
#: real pairs with no simulated distortion (30 m and 60 m windows, 70 and 112 fits; scratch
#: script, docs/verification.md): the fitted drift over its standard error had an RMS of 1.73
#: and 1.89 (1 if the errors were right; vehicle maps of traverses 8, 14 and 17 show 0.02-0.05
#: deg/m), the scale 1.64 and 1.54; with these floors 1.08 / 1.02 and 1.19 / 1.05.
DRIFT_FLOOR_DEG_PER_M = 0.02
SCALE_FLOOR = 0.002


def _sighting_placement(
    unb: "_Unbender", Pv: np.ndarray, given: bool, sighting_arcs, max_span_m: float
):
    """Where along the path each vehicle landmark was seen from (index into ``unb.path``),
    whether that is known well enough to take part in the bend fit (its arc span at most
    `max_span_m`), and the source: ``"sightings"`` (the map's sighting arcs, mean placed),
    ``"nearest path point"`` (a path without sighting arcs: a landmark that more than one pass
    of the path comes within sight of is left out, :meth:`_Unbender.passes`) or
    ``"straight stand-in"`` (no path: a straight line, passed once)."""
    if given and sighting_arcs is not None:
        mean, lo, hi = (np.asarray(a, float) for a in sighting_arcs)
        if len(mean) == len(Pv) and (not len(hi) or float(hi.max()) <= unb.arc[-1] * 1.01 + 0.5):
            return unb.index_at_arc(mean), (hi - lo) <= max_span_m, "sightings"
        log.warning(
            "bend fit: the vehicle map's sighting arcs (up to %.1f m) do not fit the given path "
            "(%.1f m); using each landmark's nearest path point",
            float(hi.max()) if len(hi) else 0.0,
            unb.arc[-1],
        )
    if given:
        return (
            unb.index(Pv),
            unb.passes(Pv, SIGHTING_RANGE_M, PASS_MARGIN_M) <= 1,
            "nearest path point",
        )
    return unb.index(Pv), np.ones(len(Pv), bool), "straight stand-in"


def bending_fit(
    T,
    Pv,
    Pr,
    inl,
    query_xyz,
    path_xyz,
    sigma_axis_m: float,
    radius_m: float,
    rounds: int = 3,
    sighting_arcs=None,
    max_sighting_span_m: float = 10.0,
    min_inliers: int = 6,
    prior_drift_rad_per_m: float | None = None,
    prior_scale_error: float | None = None,
) -> BendFit:
    """Fit a bent (heading drift) and scaled (path scale error) model of the vehicle map to
    its inliers, starting from the rigid fit T: parameters rotation vector, translation, drift
    per metre and scale error, by least squares on the 3D residuals over `sigma_axis_m` (the
    landmarks' per-axis noise; the residuals' own scale when larger). Inliers are gathered
    again under the model (mutual nearest neighbours within `radius_m`; at most `rounds` fits), so
    the part of a bent map the rigid fit left out can show its bend. Covariance from the Jacobian;
    the query points' positions and headings under the model, with their uncertainty beyond
    the rigid model's, are compared with the rigid fit's. Without `path_xyz` a straight path
    along the map's principal axis stands in (a rough proxy for a winding traverse).

    Each landmark is unbent from where it was seen: `sighting_arcs` ``(mean, min, max)`` (m of
    arc along `path_xyz`, per row of `Pv`; :attr:`LandmarkMap.sighting_arc_m`) places it at its
    mean sighting arc; one seen over more than `max_sighting_span_m` of arc (the path passed it
    twice: its aggregate mixes passes the model cannot tell apart) is left out of the fit.
    Without them, its nearest path point stands in, and a landmark that more than one pass of
    the path comes within sight of (:meth:`_Unbender.passes`) is left out. With fewer than
    `min_inliers` inliers
    left the bend is not determined: infinite sigma (refused).

    `prior_drift_rad_per_m` / `prior_scale_error`: a zero-mean Gaussian prior (1 sigma) on the drift
    and the scale error, two more residuals of the least squares (a maximum a posteriori fit): where
    the maps do not fix the bend, its uncertainty is the prior's, not metres."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    q = np.asarray(query_xyz, float).reshape(-1, 3)
    given = path_xyz is not None and len(path_xyz) >= 2
    unb = _Unbender(path_xyz if given else _straight_path(np.vstack([Pv, q])))
    idx_all, known, source = _sighting_placement(unb, Pv, given, sighting_arcs, max_sighting_span_m)
    idx_q = unb.index(q)
    if given:  # the rover at the path's end is there, not at an earlier pass that comes as near
        end = np.linalg.norm(q[:, :2] - unb.path[-1, :2], axis=1) <= QUERY_AT_END_M
        idx_q[end] = len(unb.path) - 1
    tree = cKDTree(Pr)
    R0 = Rotation.from_matrix(T[:3, :3]).as_rotvec()

    def model_T(
        x,
    ):  # Rodrigues: scipy's Rotation costs ~25 us a call here, called ~100 times per fit
        return make_transform(exp_so3(x[:3]), x[3:6])

    def apply(x, P, idx):
        return transform_points(model_T(x), unb(P, idx, x[6], x[7]))

    x = np.r_[R0, T[:3, 3], 0.0, 0.0]
    pairs = np.asarray(inl)
    pairs = pairs[known[pairs[:, 0]]]
    if len(pairs) < max(min_inliers, 3):  # the 8 parameters are not determined by what is left
        inf = math.inf
        return BendFit(
            0.0,
            inf,
            0.0,
            inf,
            inf,
            inf,
            inf,
            inf,
            0.0,
            int(len(pairs)),
            bool(given),
            source,
            int(len(inl) - len(pairs)),
            inf,
            inf,
        )
    left_out = int(len(inl) - len(pairs))
    prior_sd = (
        np.array([prior_drift_rad_per_m or math.inf, prior_scale_error or math.inf])
        if (prior_drift_rad_per_m or prior_scale_error)
        else None
    )
    chi2_rigid = chi2_bent = 0.0
    first_round = True
    for _ in range(rounds):
        v, r = pairs[:, 0], pairs[:, 1]
        used = len(pairs)

        def resid(xx):
            geo = ((apply(xx, Pv[v], idx_all[v]) - Pr[r]) / sigma_axis_m).ravel()
            return np.r_[geo, xx[6:8] / prior_sd] if prior_sd is not None else geo

        sol = least_squares(
            resid,
            x,
            x_scale=np.r_[np.full(3, 1e-3), np.full(3, 1e-2), 1e-4, 1e-3],
            method="lm",
            max_nfev=200,
        )
        if first_round:  # on the rigid fit's own inliers
            chi2_rigid, chi2_bent = float(np.sum(resid(x) ** 2)), float(np.sum(sol.fun**2))
            first_round = False
        x = sol.x
        d, j = tree.query(apply(x, Pv, idx_all), distance_upper_bound=radius_m)
        ok = np.flatnonzero(np.isfinite(d))
        order = ok[np.argsort(d[ok])]
        _, first = np.unique(j[order], return_index=True)
        new = np.stack([order[first], j[order[first]]], axis=1)
        new = new[known[new[:, 0]]]
        if len(new) <= len(pairs):
            break
        pairs = new
    J = sol.jac
    n_prior = 0 if prior_sd is None else 2
    geo = slice(0, J.shape[0] - n_prior)
    dof = max(J.shape[0] - n_prior - 8, 1)
    # residuals noisier than the stated sigma widen the data's part of the covariance (not the
    # prior's)
    s2 = max(1.0, float(np.sum(sol.fun[geo] ** 2)) / dof)
    J = J.copy()
    # the geometric rows at the noise they show; from here on C = (J^T J)^-1
    J[geo] /= math.sqrt(s2)
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        C = np.full((8, 8), np.inf)

    def at_query(xx):  # positions (3 per query point), then the map's local heading at each
        R = model_T(xx)[:3, :3]
        h = unb.heading(idx_q, xx[6])  # yaw_of(R @ rot_z(h)) for every h at once
        c, s = np.cos(h), np.sin(h)
        return np.r_[
            apply(xx, q, idx_q).ravel(),
            np.arctan2(R[1, 0] * c + R[1, 1] * s, R[0, 0] * c + R[0, 1] * s),
        ]

    f0 = at_query(x)
    Jq = np.empty((len(f0), 8))
    for i in range(8):
        h = 1e-6 if i == 6 else 1e-5
        dx = np.zeros(8)
        dx[i] = h
        Jq[:, i] = (at_query(x + dx) - at_query(x - dx)) / (2 * h)
    n = len(q)
    var = (
        np.einsum("ij,jk,ik->i", Jq, C, Jq) if np.all(np.isfinite(C)) else np.full(len(f0), np.inf)
    )
    # The bent model's uncertainty at the query points holds the rigid pose's own, which the
    # predicted error counts once as the registration's: only the increase over the rigid
    # model fitted to the same residuals is the bend's. For nested least squares that is the
    # variance of the difference between the two models' predictions.
    if np.all(np.isfinite(var)):
        try:
            C6 = np.linalg.inv(J[:, :6].T @ J[:, :6])
            var = np.maximum(var - np.einsum("ij,jk,ik->i", Jq[:, :6], C6, Jq[:, :6]), 0.0)
        except np.linalg.LinAlgError:
            pass
    # Real maps bend and stretch a little beyond what their noise says (measured floors): the
    # floors' effect at the query points with the rigid part re-fitted to the inliers (what the
    # inliers absorb of a bend does not move the pose). A 1-sigma spread, kept apart, under the
    # prior too (without it, bent maps were claimed wrong: see fitted_predicted_error).
    floor = np.array([math.radians(DRIFT_FLOOR_DEG_PER_M), SCALE_FLOOR]) ** 2
    try:
        G = Jq[:, 6:] - Jq[:, :6] @ np.linalg.solve(J[:, :6].T @ J[:, :6], J[:, :6].T @ J[:, 6:])
        var_floor = G**2 @ floor
    except np.linalg.LinAlgError:
        var_floor = np.full(len(var), np.inf)
    pos_var = var[: 3 * n].reshape(-1, 3).sum(axis=1)
    pos_floor = var_floor[: 3 * n].reshape(-1, 3).sum(axis=1)
    shift = np.linalg.norm(f0[: 3 * n].reshape(-1, 3) - transform_points(T, q), axis=1)
    dyaw = np.abs((f0[3 * n :] - yaw_of(T[:3, :3]) + math.pi) % (2 * math.pi) - math.pi)
    return BendFit(
        drift_rad_per_m=float(x[6]),
        drift_se=float(math.sqrt(max(C[6, 6], 0.0))),
        scale_error=float(x[7]),
        scale_se=float(math.sqrt(max(C[7, 7], 0.0))),
        shift_m=float(shift.max()),
        sigma_m=float(math.sqrt(max(pos_var.max(), 0.0))),
        rotation_shift_deg=math.degrees(float(dyaw.max())),
        rotation_sigma_deg=math.degrees(math.sqrt(max(float(var[3 * n :].max()), 0.0))),
        chi2_drop=chi2_rigid - chi2_bent,
        inliers=int(used),
        path_given=bool(given),
        placement=source,
        left_out=left_out,
        floor_sigma_m=float(math.sqrt(max(pos_floor.max(), 0.0))),
        rotation_floor_sigma_deg=math.degrees(math.sqrt(max(float(var_floor[3 * n :].max()), 0.0))),
    )


#: A bend the maps alone fit this many sigma (their standard error and the prior's combined) away
#: from the prior's zero is one real odometry does not make: the prior is not applied. Shrunk
#: towards the prior, a 0.1 deg/m map was claimed 14 cm off (tests/test_sighting_arcs.py), and
#: at 2 sigma pair 10-14 (0.05 deg/m, 30 m window, 1.9 sigma) 10.9 cm off (docs/verification.md)
PRIOR_CONFLICT_SIGMAS = 1.0


def prior_conflict(
    bend: "BendFit", prior_drift_rad_per_m: float | None, prior_scale_error: float | None
) -> float:
    """How far, in sigmas, the bend fitted from the maps alone lies from the zero-mean odometry
    prior: the larger of drift and scale, each over the root sum of squares of its standard
    error and the prior's sigma (a parameter without a prior does not count). Infinite when the
    fit is not finite."""
    out = 0.0
    for est, se, sd in (
        (bend.drift_rad_per_m, bend.drift_se, prior_drift_rad_per_m),
        (bend.scale_error, bend.scale_se, prior_scale_error),
    ):
        if sd is None:
            continue
        if not (math.isfinite(est) and math.isfinite(se)):
            return math.inf
        out = max(out, abs(est) / math.sqrt(se**2 + sd**2))
    return out


def fitted_predicted_error(
    bend: BendFit,
    cfg: "LocalizationConfig",
    registration_m: np.ndarray,
    registration_rot_deg: float,
) -> tuple[np.ndarray, float]:
    """Predicted 1-sigma position error (m, per query point) and rotation error (deg) when no
    odometry bounds are stated and the distortion is fitted from the maps: the fitted bend's
    shift (a bias) plus the random part, the registration's sigma and `distortion_fit_sigmas`
    times the bend's own sigma (the bend the data cannot exclude), and the measured floor on
    real maps' apparent distortion (`BendFit.floor_sigma_m`, a calibrated 1-sigma spread)
    combined in quadrature. The
    two are independent: `BendFit.sigma_m` is the bent model's uncertainty beyond the rigid
    one's, and the difference of two nested least-squares predictions is uncorrelated with the
    smaller model's. Adding the bent model's whole sigma linearly counted the registration two
    more times, and refused every compact map against a LAC grid (docs/verification.md); that
    margin had hidden a wrong bend model (landmarks placed at their nearest path point, where
    the path passed them twice), now placed where they were seen from (:func:`bending_fit`).
    The shift counts even when the bend is not significant: gating it on a chi-square test let
    a 2.3-sigma bend through (pair 4-9, 0.025 deg/m, 60 m window: 10.3 cm / 1.03 deg off,
    predicted 5.5 cm). Infinite when the fit is not finite."""
    # counted `distortion_fit_sigmas` times, under the prior too: the fit's standard errors run
    # small on real maps (DRIFT_FLOOR_DEG_PER_M), and at 1 sigma under the prior, with no floor,
    # bent maps the inliers could not see (0.05-0.1 deg/m, 11 inliers, 30 m windows: pairs 4-14,
    # 7-15) were claimed 21-24 cm off with 6.5-8.4 cm predicted
    k = cfg.distortion.fit_sigmas
    reg = np.asarray(registration_m, float)
    if not all(
        map(
            math.isfinite,
            (
                bend.shift_m,
                bend.sigma_m,
                bend.rotation_shift_deg,
                bend.rotation_sigma_deg,
                bend.floor_sigma_m,
                bend.rotation_floor_sigma_deg,
                registration_rot_deg,
            ),
        )
    ):
        return np.full(reg.shape, math.inf), math.inf
    pos = bend.shift_m + np.sqrt(reg**2 + (k * bend.sigma_m) ** 2 + bend.floor_sigma_m**2)
    rot = bend.rotation_shift_deg + math.sqrt(
        registration_rot_deg**2
        + (k * bend.rotation_sigma_deg) ** 2
        + bend.rotation_floor_sigma_deg**2
    )
    return pos, rot
