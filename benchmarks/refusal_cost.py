"""Time and memory to refuse the oversized inputs of the second hostile corpus (a 10^9- and a 10^6-job
campaign grid, a 1e9 s scenario, ``localization.epsilon_m = 10`` in --config, 100,000-deep
JSON), each case of the hostile corpus (tests/_hostile_surfaces.py) in a fresh process.

    .venv/bin/python benchmarks/refusal_cost.py                       # this checkout
    .venv/bin/python benchmarks/refusal_cost.py --src OLD/src         # another checkout's code

Per case: the outcome, the wall time of the command (imports excluded: they happen before
the clock starts), the peak RSS of the process (ru_maxrss) and the growth of that peak over
the process after imports. A case still running after --timeout seconds is stopped (a hang).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = (
    "campaign/grid-1e9-combinations",
    "campaign/grid-1e6-combinations",
    "campaign/grid-10001-combinations",
    "campaign/job-duration_s-1000000000.0",
    "config/run-epsilon-10",
    "config/bench-loop-epsilon-10",
    "config/demo-scenario-duration-1e9",
    "config/run-deep-nesting",
    "campaign/spec-deep-nesting",
)

CHILD = r"""
import json, resource, sys, tempfile, time
from pathlib import Path
sys.path.insert(0, SRC); sys.path.insert(0, TESTS)
import _hostile as H
from lunarloc.cli.app import main
import lunarloc.cli.commands_campaign, lunarloc.cli.commands_run  # imports before the clock
case = next(c for c in H.corpus() if c.name == NAME)
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
with tempfile.TemporaryDirectory() as d:
    t0 = time.perf_counter()
    o = H.run_case(case, Path(d) / "c", main, TIMEOUT)
    wall = time.perf_counter() - t0
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print("RESULT " + json.dumps({"case": NAME, "outcome": o.outcome, "rc": o.rc, "wall_s": round(wall, 2),
      "peak_rss_mib": round(rss / 1024, 1), "growth_mib": round((rss - rss0) / 1024, 1), "message": o.message[:160]}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--src", type=Path, default=ROOT / "src")
    ap.add_argument(
        "--timeout", type=int, default=60, help="seconds before a case counts as a hang"
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = []
    print(f"lunarloc from {args.src}")
    print("| case | outcome | time to outcome (s) | peak RSS (MiB) | growth over imports (MiB) |")
    print("|---|---|---|---|---|")
    for name in CASES:
        code = CHILD.replace("SRC", repr(str(args.src.resolve()))).replace(
            "TESTS", repr(str(ROOT / "tests"))
        )
        code = code.replace("NAME", repr(name)).replace("TIMEOUT", str(args.timeout))
        p = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=args.timeout + 120,
            check=False,
        )
        line = next((l for l in p.stdout.splitlines() if l.startswith("RESULT ")), None)
        if line is None:
            r = {
                "case": name,
                "outcome": f"child failed (exit {p.returncode})",
                "wall_s": None,
                "peak_rss_mib": None,
                "growth_mib": None,
                "message": p.stderr[-300:],
            }
        else:
            r = json.loads(line[7:])
        rows.append(r)
        print(
            f"| {name} | {r['outcome']} | {r['wall_s']} | {r['peak_rss_mib']} | {r['growth_mib']} |",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
