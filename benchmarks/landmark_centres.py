"""The centre error of a map's landmarks against the true rock centres, next to that of
the single detections they were clustered from (issue 11: is the localisation-relevant
centre, the landmark, within 3 cm even where single detections are not?).

Usage
-----
    python benchmarks/landmark_centres.py ARCHIVES.lac... [--config RUN.json]
        [--min-sightings 3 5] [--json OUT.json]
    python benchmarks/landmark_centres.py --det DET.csv --rocks ROCKS.csv [--det ... --rocks ...]
        [--min-sightings 3 5] [--json OUT.json]

With archives (rendered with ``custom/rocks.csv``), the detector runs over each one as
``bench_perception.py`` runs it (``detect_archive``, ground-truth poses, the run
configuration's detector scaled to the archive's width, the lander dropped). With
``--det``/``--rocks`` pairs, detections CSVs written by ``lunarloc detect --pose
ground-truth`` are read instead (e.g. the multi-session reference traverses).

Each traverse's detections are clustered as ``lunarloc map`` clusters them
(:func:`lunarloc.io.maps.traverse_map`, ``AggregationConfig`` with the given minimum
sightings). Reported, for the rocks of radius >= 0.1 m ("target") and for all rocks:

* detections: each frame's detections matched one-to-one to the true rocks within
  max(0.15 m, r) (as ``bench_perception.py`` matches them); median and p90 of the 3D,
  horizontal and |vertical| centre errors. With archives only rocks within 5 m of the
  camera count (the issue's target); with CSVs within 5 m of the rover.
* landmarks: the map's landmarks matched one-to-one to the true rocks the same way;
  the same errors, and how many landmarks lie on a rock.

Groups: per archive lighting (from its description) and "all"; with CSVs, per file.
The scoring is :mod:`lunarloc.pipeline.landmark_centres`; this prints its table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lunarloc.pipeline.landmark_centres import archive_traverse, csv_traverse, evaluate


def print_table(res: dict) -> None:
    def cm(x):
        return f"{100 * x:4.1f}"

    print(
        "group | what | items | matched | target n: 3D median/p90, horizontal median/p90, |z| median (cm) | all n: 3D median"
    )
    for g, v in res.items():
        for k, s in v.items():
            t, a = s["target"], s["all"]
            print(
                f"{g} | {k} | {s['items']} | {s['matched']} | {t['n']}: {cm(t['3d_median_m'])}/{cm(t['3d_p90_m'])}, "
                f"{cm(t['xy_median_m'])}/{cm(t['xy_p90_m'])}, {cm(t['z_abs_median_m'])} | {a['n']}: {cm(a['3d_median_m'])}"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("archives", nargs="*", type=Path)
    ap.add_argument(
        "--det", type=Path, action="append", default=[], help="detections CSV (ground-truth poses)"
    )
    ap.add_argument(
        "--rocks", type=Path, action="append", default=[], help="rocks.csv of each --det, in order"
    )
    ap.add_argument(
        "--config", type=Path, default=None, help="run configuration JSON (its detector section)"
    )
    ap.add_argument("--min-sightings", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if len(a.det) != len(a.rocks):
        ap.error("give one --rocks per --det")
    if not a.archives and not a.det:
        ap.error("give archives or --det/--rocks pairs")
    from lunarloc.config.run import RunConfig, load_config_file

    cfg = (load_config_file(a.config)[0] if a.config else RunConfig()).detector
    trs = [archive_traverse(p, cfg) for p in a.archives] + [
        csv_traverse(d, r) for d, r in zip(a.det, a.rocks)
    ]
    res = evaluate(trs, a.min_sightings)
    print_table(res)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
