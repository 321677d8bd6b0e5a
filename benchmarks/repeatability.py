"""Repeatability of the detector's rock positions over a traverse and across two sessions.

Usage
-----
    python benchmarks/repeatability.py --seeds 300 301 [--style lac|default] [--duration 90]
        [--image-rate 0.5] [--max-range 5] [--min-sightings 3] [--[no-]small-rocks] [--config RUN.json]
        [--out-dir bench-output/repeatability] [--json OUT.json]
    python benchmarks/repeatability.py --sessions A.lac B.lac [...]   # archives of one site

For each site seed two sessions are rendered (front stereo pair, 1280x720): a survey
(``TraversePlan.SURVEY``, a spiral around the lander) and a revisit of the surveyed ground
(``TraversePlan.REVISIT``), both traverse index 0 and 1 of the site. The detector runs on
every rendered frame as ``bench_perception.py`` runs it (``detect_archive``, the run
configuration's detector scaled to the archive's width, the lander dropped) with the
**ground-truth rover poses**, so the spread is perception's alone (no odometry drift).

Each detection is tied to the rock under its image centroid in the semantic image
(``lunarloc.sim.repeatability.rock_under``: no distance gate, so a misplaced detection of
a rock counts against its spread); detections farther than ``--max-range`` metres (depth)
are left out. Reported per true-radius band (``lunarloc.sim.repeatability.summarise``):
the sighting deviation (each sighting's horizontal distance from its rock's session mean),
the rock spread (its RMS per rock and session) and the session offset (the distance
between a rock's two session means), each as count, median and p90. Across the two sessions
of a site (``two_session_spread``): for each rock seen ``--min-sightings`` times in both,
every sighting's horizontal distance from the mean of all its sightings in both sessions
(sightings: n, median, p90) and its RMS per rock (rocks: n, median, p90); and the r >= 0.1 m sighting deviations by the
detection's depth (0-3, 3-4, >= 4 m: near or far sightings). Target (issue 29):
median <= 2 cm horizontal for r >= 0.1 m.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lunarloc.perception.detector import DetectorConfig, detect_archive
from lunarloc.sim.repeatability import RADIUS_BANDS_M, SightingLog, rock_under, summarise


def site_config(style: str):
    from lunarloc.sim.site import SiteConfig

    return SiteConfig.lac_style() if style == "lac" else SiteConfig()


def render_sessions(
    seed: int, style: str, duration: float, rate: float, out_dir: Path
) -> list[Path]:
    """Render (once) the survey and the revisit session of site `seed`."""
    from lunarloc.sim.render import RenderConfig
    from lunarloc.sim.rover import RoverConfig
    from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse

    out = []
    site = None
    for index, plan in enumerate(("survey", "revisit")):
        p = out_dir / f"site{seed}_{style}_{plan}_{duration:g}s.lac"
        if not p.exists():
            sc = SimulationConfig(
                site=site_config(style),
                rover=RoverConfig(plan=plan),
                duration_s=duration,
                image_rate_hz=rate,
                cameras=("FrontLeft", "FrontRight"),
                render=RenderConfig.lac_style() if style == "lac" else RenderConfig(),
            )
            site = site or simulate_site(seed, sc)
            out_dir.mkdir(parents=True, exist_ok=True)
            t0 = time.process_time()
            simulate_traverse(site, p, index, sc)
            print(f"rendered {p} ({time.process_time() - t0:.0f} s CPU)", file=sys.stderr)
        out.append(p)
    return out


def log_session(
    path: Path,
    session: str,
    cfg: DetectorConfig,
    log: SightingLog,
    max_range: float,
    depths: dict | None = None,
) -> dict:
    """Detect over one archive (ground-truth poses) and log each detection's rock (and, with
    `depths`, its depth in metres under (session, rock), in the log's order). Returns the
    counts of detections: on a rock, on no rock, beyond range."""
    from lunarloc.config.run import scaled_detector_config
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import camera_from_archive
    from lunarloc.perception.detector import Detector
    from lunarloc.pipeline.perception_eval import lander_xy

    counts = {"on_rock": 0, "off_rock": 0, "beyond_range": 0}
    with LacArchive(path) as ar:
        t = ar.custom("rocks")
        radii = {int(i): float(r) for i, r in zip(t["id"], t["radius"])}
        cam = camera_from_archive(ar)
        det = Detector(scaled_detector_config(cam.width, base=cfg), cam)
        for fd in detect_archive(
            ar, det.config, "ground-truth", detector=det, lander_xy=lander_xy(ar)
        ):
            sems = {}
            for d in fd.detections:
                if d.depth_m > max_range:
                    counts["beyond_range"] += 1
                    continue
                if d.camera not in sems:
                    sems[d.camera] = ar.semantic(d.camera, fd.frame)
                rock = rock_under(sems[d.camera], d.uv)
                if rock < 0:
                    counts["off_rock"] += 1
                    continue
                counts["on_rock"] += 1
                log.add(session, rock, d.p_map[:2])
                if depths is not None:
                    depths.setdefault((session, rock), []).append(float(d.depth_m))
    return {"radii": radii, **counts}


def _stats(values: list[float]) -> dict:
    a = np.asarray(values, float)
    if a.size == 0:
        return {"n": 0, "median_m": float("nan"), "p90_m": float("nan")}
    return {"n": int(a.size), "median_m": float(np.median(a)), "p90_m": float(np.percentile(a, 90))}


def two_session_spread(log: SightingLog, radii_m: dict[int, float], min_sightings: int) -> dict:
    """Spread of each rock's sightings across the sessions of its site, by true-radius band.

    Rock ids are per site (the caller keys them so), so only a rock's own site's sessions
    pool. A rock counts when at least two sessions saw it `min_sightings` times or
    more; its sightings in those sessions are pooled, and each one's horizontal distance
    from the pooled mean is a deviation. Returns ``{band: {"sightings": stats, "rock_rms":
    stats}}`` (stats: n, median_m, p90_m), with a pooled ``"r>=0.1"`` entry.
    """
    names = [f"{lo:g}-{hi:g}" if hi < 10 else f">={lo:g}" for lo, hi in RADIUS_BANDS_M]
    dev: dict[str, list[float]] = {n: [] for n in names + ["r>=0.1"]}
    rms: dict[str, list[float]] = {n: [] for n in names + ["r>=0.1"]}
    pooled: dict[int, list[list[tuple[float, float]]]] = {}
    for rocks in log.sightings.values():
        for rock, pts in rocks.items():
            if len(pts) >= min_sightings:
                pooled.setdefault(rock, []).append(pts)
    for rock, groups in pooled.items():
        if len(groups) < 2 or rock not in radii_m:
            continue
        p = np.asarray([xy for g in groups for xy in g], float)
        d = np.hypot(*(p - p.mean(axis=0)).T)
        r = radii_m[rock]
        keys = [n for n, (lo, hi) in zip(names, RADIUS_BANDS_M) if lo <= r < hi]
        for k in keys + (["r>=0.1"] if r >= 0.1 else []):
            dev[k].extend(d.tolist())
            rms[k].append(float(np.sqrt(np.mean(d * d))))
    return {n: {"sightings": _stats(dev[n]), "rock_rms": _stats(rms[n])} for n in dev}


DEPTH_BANDS_M = ((0.0, 3.0), (3.0, 4.0), (4.0, 1e9))
"""Detection-depth bands of the by-depth breakdown (metres)."""


def deviation_by_depth(
    log: SightingLog, depths: dict, radii_m: dict, min_sightings: int, min_radius_m: float = 0.1
) -> dict:
    """Sighting deviations (each sighting from its rock's session mean, as ``summarise``) of
    the rocks of true radius >= `min_radius_m`, by the sighting's detection depth band
    (DEPTH_BANDS_M): which sightings, near or far, carry the spread. `log` and `depths` keyed
    by (session, rock) as ``log_session`` fills them, `radii_m` by (session, rock)."""
    out: dict[str, list[float]] = {
        f"{lo:g}-{hi:g}" if hi < 1e8 else f">={lo:g}": [] for lo, hi in DEPTH_BANDS_M
    }
    names = list(out)
    for session, rocks in log.sightings.items():
        for rock, pts in rocks.items():
            if len(pts) < min_sightings or radii_m.get((session, rock), 0.0) < min_radius_m:
                continue
            p = np.asarray(pts, float)
            dev = np.hypot(*(p - p.mean(axis=0)).T)
            for d, z in zip(dev, depths[(session, rock)]):
                for n, (lo, hi) in zip(names, DEPTH_BANDS_M):
                    if lo <= z < hi:
                        out[n].append(float(d))
    return {n: _stats(v) for n, v in out.items()}


def print_table(s: dict, two: dict | None = None) -> None:
    print(
        "band (true r, m) | sightings: n, median, p90 cm | rock spread: rocks, median, p90 cm | "
        "session offset: rocks, median, p90 cm"
    )
    for band, v in s.items():
        row = [band]
        for k in ("sighting_deviation", "rock_spread", "session_offset"):
            st = v[k]
            row.append(f"{st['n']}, {100 * st['median_m']:.1f}, {100 * st['p90_m']:.1f}")
        print(" | ".join(row))
    if two is None:
        return
    print(
        "across both sessions (rocks seen in both): band | sightings from the two-session mean: "
        "n, median, p90 cm | per-rock RMS: rocks, median, p90 cm"
    )
    for band, v in two.items():
        row = [band]
        for k in ("sightings", "rock_rms"):
            st = v[k]
            row.append(f"{st['n']}, {100 * st['median_m']:.1f}, {100 * st['p90_m']:.1f}")
        print(" | ".join(row))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", type=int, nargs="*", default=[])
    ap.add_argument(
        "--sessions", type=Path, nargs="*", default=[], help="archives of one site (each a session)"
    )
    ap.add_argument(
        "--style", choices=("lac", "default"), default="lac", help="site style of rendered seeds"
    )
    ap.add_argument("--duration", type=float, default=90.0, help="seconds per session")
    ap.add_argument("--image-rate", type=float, default=0.5, help="camera rate, Hz")
    ap.add_argument(
        "--max-range", type=float, default=5.0, help="leave out detections deeper than this, m"
    )
    ap.add_argument("--min-sightings", type=int, default=3)
    ap.add_argument(
        "--small-rocks",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the small-rock stage on or off (on by default)",
    )
    ap.add_argument(
        "--config", type=Path, default=None, help="a run configuration: its detector section"
    )
    ap.add_argument("--out-dir", type=Path, default=Path("bench-output/repeatability-v2"))
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    cfg = DetectorConfig()
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        cfg = load_config_file(a.config)[0].detector
    if a.small_rocks is not None:
        cfg = replace(cfg, small_rocks=replace(cfg.small_rocks, enabled=a.small_rocks))
    groups = [
        (f"site{s}", render_sessions(s, a.style, a.duration, a.image_rate, a.out_dir))
        for s in a.seeds
    ]
    if a.sessions:
        groups.append(("given", list(a.sessions)))
    if not groups:
        ap.error("give --seeds or --sessions")
    log = SightingLog()
    depths: dict = {}
    session_radii: dict = {}
    radii: dict[int, float] = {}
    counts = {"on_rock": 0, "off_rock": 0, "beyond_range": 0}
    c0 = time.process_time()
    for name, paths in groups:
        for p in paths:
            out = log_session(p, f"{name}/{p.stem}", cfg, log, a.max_range, depths)
            session_radii.update({(f"{name}/{p.stem}", r): v for r, v in out["radii"].items()})
            # rock ids are per site: key them by site so two sites' rocks stay apart
            for k in counts:
                counts[k] += out[k]
            radii.update({(name, r): v for r, v in out["radii"].items()})
    # re-key the log by (site, rock) so rocks of different sites never pool
    keyed = SightingLog()
    keyed_radii: dict[int, float] = {}
    ids: dict[tuple, int] = {}
    for session, rocks in log.sightings.items():
        site = session.split("/")[0]
        for rock, pts in rocks.items():
            k = ids.setdefault((site, rock), len(ids))
            keyed_radii[k] = radii[(site, rock)]
            for xy in pts:
                keyed.add(session.split("/")[1], k, xy)
    s = summarise(keyed, keyed_radii, a.min_sightings)
    two = two_session_spread(keyed, keyed_radii, a.min_sightings)
    print(
        f"sites: {[g[0] for g in groups]}; detections within {a.max_range:g} m: {counts['on_rock']} on a rock, "
        f"{counts['off_rock']} on no rock; {counts['beyond_range']} beyond; small rocks "
        f"{'on' if cfg.small_rocks.enabled else 'off'}; ground-truth poses; {time.process_time() - c0:.0f} s CPU"
    )
    print_table(s, two)
    by_depth = deviation_by_depth(log, depths, session_radii, a.min_sightings)
    print(
        "r>=0.1 sightings by detection depth (m): band | n, median, p90 cm of the deviation "
        "from the rock's session mean"
    )
    for band, st in by_depth.items():
        print(f"{band} | {st['n']}, {100 * st['median_m']:.1f}, {100 * st['p90_m']:.1f}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(
            json.dumps(
                {
                    "summary": s,
                    "two_session_spread": two,
                    "r>=0.1_by_depth": by_depth,
                    "counts": counts,
                    "archives": [str(p) for _, ps in groups for p in ps],
                    "small_rocks": cfg.small_rocks.enabled,
                    "max_range_m": a.max_range,
                    "min_sightings": a.min_sightings,
                },
                indent=2,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
