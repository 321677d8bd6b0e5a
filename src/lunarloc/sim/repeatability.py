"""Repeatability of rock positions: does the same rock land in the same place every time it
is seen, from any side, in any session? (issue 29; it replaces the centre-error target).

Detections are tied to the simulated rock they lie on by the renderer's semantic image
(the rock id under the detection's image centroid), not by a distance gate, so a badly
placed detection of a rock still counts against that rock's spread instead of going
unmatched. Place the detections with ground-truth rover poses and the spread is
perception's alone (no odometry drift in it).

Per rock and session (a traverse) with at least ``min_sightings`` sightings:

* *sighting deviation*: the horizontal distance of each sighting from the mean of that
  rock's sightings in the session;
* *rock spread*: the root mean square of its sighting deviations;

and per rock seen (that often) in two sessions, the *session offset*: the horizontal
distance between its two session means. Each is summarised (count, median, p90) by
true-radius band.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lunarloc.core.errors import InputError
from lunarloc.sim.render import semantic_to_rock_id

__all__ = ["RADIUS_BANDS_M", "SightingLog", "rock_under", "summarise"]

RADIUS_BANDS_M: tuple[tuple[float, float], ...] = (
    (0.025, 0.05),
    (0.05, 0.1),
    (0.1, 0.2),
    (0.2, 0.4),
    (0.4, 10.0),
)
"""True-radius bands of the summary (metres); "r>=0.1" pools the last three."""


def rock_under(semantic: np.ndarray, uv, half_window_px: int = 3) -> int:
    """The rock id that covers most of the (2h+1)^2 window at pixel ``uv`` (u, v) of a
    semantic id image, or -1 when rocks cover less than half of it."""
    sem = np.asarray(semantic)
    if sem.ndim != 2:
        raise InputError(f"semantic image must be (H, W), got shape {sem.shape}")
    u, v = round(float(uv[0])), round(float(uv[1]))
    h = int(half_window_px)
    win = semantic_to_rock_id(sem[max(v - h, 0) : v + h + 1, max(u - h, 0) : u + h + 1])
    rid = win[win >= 0]
    if win.size == 0 or rid.size * 2 < win.size:
        return -1
    return int(np.bincount(rid).argmax())


@dataclass
class SightingLog:
    """Horizontal positions (site frame, metres) of each rock's sightings, per session."""

    sightings: dict[str, dict[int, list[tuple[float, float]]]] = field(default_factory=dict)

    def add(self, session: str, rock_id: int, xy) -> None:
        xy = np.asarray(xy, float).reshape(-1)[:2]
        if not np.all(np.isfinite(xy)):
            raise InputError(f"sighting of rock {rock_id} is not finite: {xy.tolist()}")
        self.sightings.setdefault(str(session), {}).setdefault(int(rock_id), []).append(
            (float(xy[0]), float(xy[1]))
        )

    def n_sightings(self) -> int:
        return sum(len(v) for s in self.sightings.values() for v in s.values())


def _stats(values: list[float]) -> dict:
    a = np.asarray(values, float)
    if a.size == 0:
        return {"n": 0, "median_m": float("nan"), "p90_m": float("nan")}
    return {"n": int(a.size), "median_m": float(np.median(a)), "p90_m": float(np.percentile(a, 90))}


def summarise(
    log: SightingLog,
    radii_m: dict[int, float],
    min_sightings: int = 3,
    bands: tuple[tuple[float, float], ...] = RADIUS_BANDS_M,
) -> dict:
    """The repeatability figures of `log` by true-radius band (`radii_m`: rock id -> radius).

    Returns ``{band name: {"sighting_deviation": stats, "rock_spread": stats,
    "session_offset": stats}}`` (stats: n, median_m, p90_m; n counts sightings, rocks and
    rock pairs respectively), with a pooled ``"r>=0.1"`` entry.
    """
    if min_sightings < 2:
        raise InputError(
            f"min_sightings={min_sightings} must be >= 2 (a spread needs two sightings)"
        )
    names = [f"{lo:g}-{hi:g}" if hi < 10 else f">={lo:g}" for lo, hi in bands]
    dev: dict[str, list[float]] = {n: [] for n in names + ["r>=0.1"]}
    spread: dict[str, list[float]] = {n: [] for n in names + ["r>=0.1"]}
    offset: dict[str, list[float]] = {n: [] for n in names + ["r>=0.1"]}
    means: dict[int, list[np.ndarray]] = {}

    def keys(rock: int) -> list[str]:
        r = radii_m.get(rock)
        if r is None:
            return []
        out = [n for n, (lo, hi) in zip(names, bands) if lo <= r < hi]
        return out + (["r>=0.1"] if r >= 0.1 else [])

    for session in sorted(log.sightings):
        for rock, pts in log.sightings[session].items():
            if len(pts) < min_sightings:
                continue
            p = np.asarray(pts, float)
            mean = p.mean(axis=0)
            d = np.hypot(*(p - mean).T)
            means.setdefault(rock, []).append(mean)
            for k in keys(rock):
                dev[k].extend(d.tolist())
                spread[k].append(float(np.sqrt(np.mean(d * d))))
    for rock, ms in means.items():
        for i in range(len(ms)):
            for j in range(i + 1, len(ms)):
                for k in keys(rock):
                    offset[k].append(float(np.hypot(*(ms[i] - ms[j]))))
    return {
        n: {
            "sighting_deviation": _stats(dev[n]),
            "rock_spread": _stats(spread[n]),
            "session_offset": _stats(offset[n]),
        }
        for n in names + ["r>=0.1"]
    }
