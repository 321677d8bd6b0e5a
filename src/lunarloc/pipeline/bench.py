"""The benchmarks behind ``lunarloc bench``: what they run, check and write (the CLI prints).

- :func:`bench_loop`: the online loop on every real LunarLoc traverse (world-frame
  detections, simulated odometry drift), each localized against a map of all the others;
  one run folder per traverse plus ``loop.json``.
- :func:`pairs_to_run`, :func:`pairs_problems`, :func:`write_pairs`: the traverse-pair
  benchmark's pair list, its acceptance check and its ``pairs.csv`` / ``pairs.json``
  (the localization itself is :func:`lunarloc.pipeline.evaluation.bench_pairs`).
"""

from __future__ import annotations

import csv
import itertools
import json
from pathlib import Path
from typing import Callable, Iterable

from lunarloc.config.run import RunConfig
from lunarloc.core.errors import ConfigError

__all__ = [
    "bench_loop",
    "pairs_to_run",
    "pairs_problems",
    "write_pairs",
    "MIN_PAIRS_CORRECT",
    "PAPER_MAX_ERR_M",
]

MIN_PAIRS_CORRECT = 130  # of the 136 pairs, success claimed and correct (the CI gate)
PAPER_MAX_ERR_M = 0.02  # each paper pair: error at the reference origin below this


def bench_loop(
    data: str | Path,
    out: str | Path,
    config: RunConfig | None = None,
    *,
    traverses: Iterable[int] | None = None,
    min_length_m: float = 5.0,
    on_traverse: Callable[[dict], None] | None = None,
) -> list[dict]:
    """Run the loop on each traverse of `data` (default all; shorter than `min_length_m`
    skipped) against the merged detections of all the others, write ``out/traverse_N/`` run
    folders and ``out/loop.json``; returns the summaries (``vehicle`` added), each also
    passed to `on_traverse` as it is done.

    config : default :meth:`RunConfig.for_detections`; its odometry section gives the
        simulated drift and frame rate."""
    from lunarloc.pipeline.evaluation import find_traverses
    from lunarloc.io.maps import load_traverse
    from lunarloc.io.outputs import atomic_open
    from lunarloc.pipeline.runner import run
    from lunarloc.pipeline.reference import reference_from_traverses
    from lunarloc.io.runs import write_run
    from lunarloc.pipeline.sources import TraverseCsvSource

    cfg = config or RunConfig.for_detections()
    out = Path(out)
    trav = {k: load_traverse(p) for k, p in find_traverses(data).items()}
    wanted = list(traverses) if traverses is not None else sorted(trav)
    missing = [v for v in wanted if v not in trav]
    if missing:
        raise ConfigError(
            f"traverse(s) {', '.join(map(str, missing))} not in {data} (have "
            f"{', '.join(map(str, trav))})"
        )
    rows = []
    for v in wanted:
        if trav[v].path_length < min_length_m:
            continue
        ref = reference_from_traverses(trav, exclude=v)
        src = TraverseCsvSource.for_run(trav[v], cfg)
        s = write_run(run(src, ref, cfg), out / f"traverse_{v}")
        s["vehicle"] = v
        rows.append(s)
        if on_traverse:
            on_traverse(s)
    with atomic_open(out / "loop.json", "w") as fh:
        fh.write(json.dumps(rows, indent=1))
    return rows


def pairs_to_run(traverses: Iterable[int], only_paper: bool = False) -> list[tuple[int, int]]:
    """The paper's five pairs first, then (unless `only_paper`) every other unordered pair."""
    from lunarloc.pipeline.evaluation import PAPER_PAIRS

    if only_paper:
        return list(PAPER_PAIRS)
    return list(PAPER_PAIRS) + [
        p for p in itertools.combinations(sorted(traverses), 2) if p not in PAPER_PAIRS
    ]


def pairs_problems(summary, only_paper: bool = False) -> list[str]:
    """The pair benchmark's acceptance check (empty when it passes): every paper pair
    localized within ``PAPER_MAX_ERR_M`` at the origin, at least ``MIN_PAIRS_CORRECT`` pairs
    claimed and correct (all pairs), no confident-wrong pair."""
    from lunarloc.pipeline.evaluation import PAPER_PAIRS

    bad = []
    for r in summary.results:
        if (r.reference, r.vehicle) in PAPER_PAIRS and not (
            r.success and r.err_origin_m < PAPER_MAX_ERR_M
        ):
            bad.append(
                f"paper pair {r.reference}-{r.vehicle}: success={r.success} "
                f"err={r.err_origin_m * 100:.2f} cm"
            )
    if not only_paper and summary.n_success_and_correct < MIN_PAIRS_CORRECT:
        bad.append(
            f"only {summary.n_success_and_correct} of {summary.n_pairs} pairs localized correctly "
            f"(need {MIN_PAIRS_CORRECT})"
        )
    if summary.n_confident_wrong:
        bad.append(f"{summary.n_confident_wrong} confident-wrong pairs")
    return bad


def write_pairs(summary, out: str | Path) -> tuple[Path, Path]:
    """``out/pairs.json`` (the summary) and ``out/pairs.csv`` (one row per pair)."""
    from lunarloc.io.outputs import atomic_open, write_text

    out = Path(out)
    d = summary.to_dict()
    write_text(out / "pairs.json", json.dumps(d, indent=1))
    with atomic_open(out / "pairs.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        keys = list(d["results"][0].keys()) if d["results"] else []
        w.writerow(keys)
        for row in d["results"]:
            w.writerow([row[k] for k in keys])
    return out / "pairs.csv", out / "pairs.json"
