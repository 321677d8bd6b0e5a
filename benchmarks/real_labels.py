"""Score the rock detector on the hand-labelled real LAC pairs (tests/data/lac_real_labels.json).

    python benchmarks/real_labels.py [--data DIR] [--labels JSON] [--config RUN_CONFIG.json] [--[no-]small-rocks]
        [--frames lac99 ipex179 ...] [--misses OUT.csv] [--figure-dir DIR] [--json OUT.json]

DIR defaults to $LUNARLOC_LAC_REAL or ../shared/data/lac-real. Each pair runs once through
`Detector.detect_pair` with the IPEx front-left mount; frame 99 with its ground-truth pose and the
lander at the site centre (as `bench_perception --lac-real`), the ipex frames with no pose (their
roll and pitch are unknown: the rover frame is the detector's only frame).

The scoring is :mod:`lunarloc.pipeline.real_labels` (see tests/data/README.md): a detection is *on* a rock when its image point lies in the
rock's box grown by GROW_PX and its depth is within a factor 1.6 of the rock's range; a rock is
found when a detection is on it. Recall counts certain rocks with range <= recall_range_m (6 m);
detections on uncertain rocks are ignored; every other detection is false, and those on a no-fire
region (lander, rover shadow) are counted apart. For each missed rock, the stage that lost it
(`lunarloc.pipeline.perception_eval.miss_stage`: the mask overlapping its box most and that mask's reject reason,
or no blob with the share of the box that has a height and the highest height there).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from lunarloc.core.errors import MissingFileError
from lunarloc.pipeline.real_labels import load_labels, run, summarize

HERE = Path(__file__).resolve().parent

LABELS = HERE.parent / "tests" / "data" / "lac_real_labels.json"


def default_data_dir() -> Path:
    return Path(
        os.environ.get("LUNARLOC_LAC_REAL", HERE.parent.parent / "shared" / "data" / "lac-real")
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--labels", type=Path, default=LABELS)
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="a run configuration whose detector section is used",
    )
    ap.add_argument("--frames", nargs="*", default=None)
    ap.add_argument(
        "--small-rocks",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the small-rock stage on or off (DetectorConfig.small_rocks.enabled; on by default)",
    )
    ap.add_argument(
        "--misses", type=Path, default=None, help="write each missed rock and its stage to this CSV"
    )
    ap.add_argument("--figure-dir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    data = a.data or default_data_dir()
    cfg = None
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        cfg = load_config_file(a.config)[0].detector
    if a.small_rocks is not None:
        from dataclasses import replace

        from lunarloc.perception.detector import DetectorConfig

        base = cfg or DetectorConfig()
        cfg = replace(base, small_rocks=replace(base.small_rocks, enabled=a.small_rocks))
    misses: list | None = [] if a.misses is not None else None
    try:
        res = run(data, load_labels(a.labels), cfg, a.frames, misses, a.figure_dir)
    except MissingFileError as e:
        raise SystemExit(str(e)) from None
    for f in res["frames"]:
        s = summarize([f])
        print(
            f"{f['frame']:9s} rocks {s['recall_all'][0]:2d}/{s['recall_all'][1]:2d}  >=8cm {s['recall_ge_8cm'][0]}/"
            f"{s['recall_ge_8cm'][1]}  detections {s['detections']:2d}: on rocks {s['on_rocks']}, false {s['false']}"
            f" (no-fire {s['on_no_fire']}), uncertain {s['on_uncertain']}"
        )
    s = res["summary"]
    print(
        "all: recall {0[0]}/{0[1]} = {0[2]}; >= 8 cm {1[0]}/{1[1]} = {1[2]}; < 8 cm {2[0]}/{2[1]} = {2[2]}".format(
            s["recall_all"], s["recall_ge_8cm"], s["recall_lt_8cm"]
        )
    )
    print(
        "     by range: " + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in s["recall_by_range"].items())
    )
    print(
        f"     detections {s['detections']}: on rocks {s['on_rocks']}, false {s['false']} (on no-fire regions "
        f"{s['on_no_fire']}), on uncertain labels {s['on_uncertain']}; precision {s['precision']}; "
        f"{s['wall_ms_per_pair_median']} ms per pair (wall, median)"
    )
    if misses is not None:
        import csv
        from collections import Counter

        a.misses.parent.mkdir(parents=True, exist_ok=True)
        if misses:
            with open(a.misses, "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(misses[0]))
                w.writeheader()
                for r in misses:
                    w.writerow(
                        {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()}
                    )
        print(
            "missed rocks by stage: "
            + ", ".join(f"{k} {v}" for k, v in Counter(r["stage"] for r in misses).most_common())
        )
        for r in misses:
            print(
                f"  {r['rock_id']:7s} {r['width_m']:.3f} m wide at {r['range_m']:.2f} m: {r['stage']}"
                + (f" ({r['tentative_rules']})" if r.get("tentative_rules") else "")
                + (
                    f" valid {r['valid_fraction']:.2f} max height {r['max_height_m']:.3f} m"
                    if r["stage"] == "no-blob"
                    else f" overlap {r['overlap']:.2f}"
                )
            )
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
