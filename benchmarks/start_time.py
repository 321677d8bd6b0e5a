"""Cold and warm start of ``lunarloc localize REF VEH --json``, and where a warm call's time goes.

* **warm**: after ``make`` (which runs ``lunarloc warm-up``): the ahead-of-time kernels are
  built (``lunarloc.association.aot``) and numba's cache holds the JIT kernels; each run is a
  fresh process. ``--jit`` times the JIT fallback instead (``LUNARLOC_AOT=0``: numba's cache,
  no ahead-of-time build).
* **cold**: as on a first call after installing without the warm-up step: no ahead-of-time
  build (``LUNARLOC_AOT=0``) and an empty ``NUMBA_CACHE_DIR`` (a new temporary folder), so the
  kernels are compiled in that process.

Each run is timed from outside (wall clock, and the child's CPU time, user + system, from
``resource.getrusage(RUSAGE_CHILDREN)``): CPU time hardly depends on how loaded the
machine is, wall time does. ``--split`` also times the stages of one warm call inside one
process (imports, map loading, the first localization, which loads the kernels, and a
second one). ``--other-python PY`` interleaves every warm run with one of the same command
under another interpreter (e.g. another checkout's ``.venv/bin/python``), so that both see
the same load.

The pair: the landmark map of real traverse 3 as the reference and traverse 7's map moved
into a vehicle frame by a fixed rigid transform (both built from ``--data`` into a
temporary folder).

Usage::

    python benchmarks/start_time.py --data ../shared/data/lunarloc-data [--runs 5] [--cold-runs 5] [--split]
        [--jit] [--other-python OTHER/.venv/bin/python]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SPLIT = r"""
import sys, time
t0, c0 = time.perf_counter(), time.process_time()
rows = []
def mark(label, s={"t": t0, "c": c0}):
    t, c = time.perf_counter(), time.process_time()
    rows.append((label, t - s["t"], c - s["c"]))
    s["t"], s["c"] = t, c
import numpy; mark("import numpy")
import typer, rich.console; mark("import typer, rich")
import scipy.spatial; mark("import scipy.spatial")
import lunarloc.localization.localize, lunarloc.localization.large; mark("import lunarloc.localization.localize")
from lunarloc.cli.app import _register_commands; _register_commands(["localize"]); mark("import the CLI command")
import lunarloc.config.run; mark("import lunarloc.config.run (RunConfig)")
from pathlib import Path
from lunarloc.pipeline.reference import load_reference
from lunarloc.io.maps import load_map
ref, veh = load_reference(Path(sys.argv[1])), load_map(sys.argv[2]); mark("load the two maps")
from lunarloc.localization.large import localize_large
import scipy.optimize; mark("import scipy.optimize (distortion fit)")
localize_large(ref, veh); mark("first localize (loads the kernels)")
localize_large(ref, veh); mark("second localize")
for label, w, c in rows:
    print(f"  {label:40s} wall {w:6.3f} s  CPU {c:6.3f} s")
from lunarloc.association.aot import aot_status
print(f"  ahead-of-time kernels: {aot_status()}; numba imported: {'numba' in sys.modules}")
"""


def _pair(data: Path, out: Path) -> tuple[Path, Path]:
    import numpy as np

    from lunarloc.core.geometry import euler_to_rotation, make_transform, transform_points
    from lunarloc.io.maps import (
        AggregationConfig,
        LandmarkMap,
        aggregate_detections,
        load_traverse,
        save_map,
    )

    maps = []
    for k in (3, 7):
        t = load_traverse(data / "csv" / f"traverse_{k}.csv")
        maps.append(
            aggregate_detections(
                t.detections_xyz, t.detection_frame, AggregationConfig(), frame=t.name
            )
        )
    ref, m = maps
    T = make_transform(euler_to_rotation(0.004, -0.006, 1.9), np.array([37.0, -12.0, 0.4]))
    veh = LandmarkMap(
        transform_points(T, m.positions_xyz),
        m.sizes,
        m.sightings,
        "vehicle",
        m.sigma_xy_m,
        m.sigma_z_m,
    )
    paths = out / "reference.csv", out / "vehicle.csv"
    save_map(ref, paths[0])
    save_map(veh, paths[1])
    return paths


def _run(cmd: list[str], env: dict) -> tuple[float, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    # the pose's acceptance is not what is timed here (one-shot localize states no odometry
    # bounds, so this pair's answer is refused as too uncertain); a JSON answer is required
    if proc.returncode != 0 or '"success": ' not in proc.stdout:
        raise SystemExit(f"run failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _report(name: str, runs: list[tuple[float, float]]) -> None:
    walls = [w for w, _ in runs]
    cpus = [c for _, c in runs]
    print(
        f"{name}: {len(runs)} runs; wall median {statistics.median(walls):.2f} s (min {min(walls):.2f}, "
        f"max {max(walls):.2f}); CPU median {statistics.median(cpus):.2f} s (min {min(cpus):.2f}, max {max(cpus):.2f})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--data", type=Path, required=True, help="lunarloc-data folder (csv/traverse_N.csv)"
    )
    ap.add_argument("--runs", type=int, default=5, help="warm runs")
    ap.add_argument(
        "--cold-runs", type=int, default=5, help="cold runs (each compiles every kernel)"
    )
    ap.add_argument(
        "--split", action="store_true", help="also time the stages of one warm call in one process"
    )
    ap.add_argument(
        "--jit", action="store_true", help="warm runs on numba's cache only (LUNARLOC_AOT=0)"
    )
    ap.add_argument(
        "--other-python", type=Path, help="interleave each warm run with one under this interpreter"
    )
    ap.add_argument(
        "--src",
        type=Path,
        help="run the lunarloc found in this source folder (PYTHONPATH), e.g. an "
        "older commit unpacked with `git archive REV src | tar -x -C DIR` (pass DIR/src)",
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="lunarloc-start-") as tmp:
        ref, veh = _pair(args.data, Path(tmp))
        cmd = [sys.executable, "-m", "lunarloc", "localize", str(ref), str(veh), "--json"]
        env = dict(os.environ)
        env.pop("NUMBA_CACHE_DIR", None)
        env.pop("LUNARLOC_AOT", None)
        if args.jit:
            env["LUNARLOC_AOT"] = "0"
        if args.src is not None:
            env["PYTHONPATH"] = str(args.src.resolve())
        other = None if args.other_python is None else [str(args.other_python), *cmd[1:]]
        _run(cmd, env)  # make sure the ordinary cache is warm
        if other:
            _run(other, env)
        print(f"load average {os.getloadavg()[0]:.1f} at start")
        warm, warm_other = [], []
        for k in range(args.runs):
            pair = [(warm, cmd)] + ([(warm_other, other)] if other else [])
            for runs, c in pair if k % 2 == 0 else pair[::-1]:  # alternate which goes first
                runs.append(_run(c, env))
        _report("warm" + (" (numba's cache, LUNARLOC_AOT=0)" if args.jit else ""), warm)
        if other:
            _report(f"warm, {args.other_python}", warm_other)
        cold = []
        for _ in range(args.cold_runs):
            with tempfile.TemporaryDirectory(prefix="numba-cold-") as cache:
                cold.append(_run(cmd, dict(env, NUMBA_CACHE_DIR=cache, LUNARLOC_AOT="0")))
        if cold:
            _report("cold (empty numba cache)", cold)
        if args.split:
            print("one warm call, by stage:")
            subprocess.run([sys.executable, "-c", SPLIT, str(ref), str(veh)], env=env, check=True)
        print(f"load average {os.getloadavg()[0]:.1f} at end")


if __name__ == "__main__":
    main()
