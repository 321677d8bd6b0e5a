"""Run the generated corpus of hostile inputs (tests/_hostile.py) through the CLI and count
outcomes: clear error, correct result, traceback, silent garbage, internal error, hang, other.

    .venv/bin/python benchmarks/hostile_inputs.py                 # the code in this checkout
    .venv/bin/python benchmarks/hostile_inputs.py --src OLD/src   # another checkout's code
    .venv/bin/python benchmarks/hostile_inputs.py --json out.json --no-slow
    .venv/bin/python benchmarks/hostile_inputs.py --kinds api,campaign,config,score,archive  # the second corpus (the API, campaigns, configs, ...)

Each case runs in-process through ``lunarloc.cli.app.main`` in its own temporary folder (the
working directory is that folder). The address space is capped (--max-gib) so a memory bomb
in old code fails with MemoryError instead of taking the machine down.
"""

from __future__ import annotations

import argparse
import collections
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--src", type=Path, default=ROOT / "src", help="the src/ folder whose lunarloc to test"
    )
    ap.add_argument("--json", type=Path, help="write every outcome here")
    ap.add_argument("--no-slow", action="store_true", help="leave out the few slow cases")
    ap.add_argument("--max-gib", type=float, default=12.0, help="address-space cap (GiB)")
    ap.add_argument("--only", default="", help="run only cases whose name contains this")
    ap.add_argument(
        "--kinds",
        default="",
        help="comma-separated kinds to run (csv,npz,lac,option,output,api,campaign,config,score,archive)",
    )
    ap.add_argument(
        "--case-timeout", type=int, default=60, help="seconds before a case counts as a hang"
    )
    args = ap.parse_args()
    sys.path.insert(0, str(args.src.resolve()))
    sys.path.insert(0, str(ROOT / "tests"))
    cap = int(args.max_gib * 1024**3)
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    import lunarloc
    from lunarloc.cli.app import main as cli_main
    from _hostile import OUTCOMES, corpus, run_case

    print(f"lunarloc from {Path(lunarloc.__file__).parent}", flush=True)
    tw = time.perf_counter()
    from lunarloc.localization.warmup import warm_up

    warm_up()  # compile the kernels first: a cold numba cache is not a hang of the first case that localizes
    print(f"kernels warmed up in {time.perf_counter() - tw:.0f} s", flush=True)
    kinds = set(filter(None, args.kinds.split(",")))
    cases = [
        c
        for c in corpus(include_slow=not args.no_slow)
        if args.only in c.name and (not kinds or c.kind in kinds)
    ]
    results = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="hostile-") as tmp:
        for i, case in enumerate(cases):
            ts = time.perf_counter()
            try:
                o = run_case(case, Path(tmp) / f"c{i:03d}", cli_main, args.case_timeout)
            except MemoryError:
                from _hostile import Outcome

                o = Outcome(
                    case.name, case.kind, "traceback", None, "MemoryError while building or running"
                )
            o.detail["time_s"] = round(time.perf_counter() - ts, 3)
            results.append(o)
            if o.outcome not in ("clear error", "correct result"):
                print(f"  {o.outcome:15s} {case.name}: rc={o.rc} {o.message[:150]}", flush=True)
    wall = time.perf_counter() - t0
    kinds = sorted({o.kind for o in results})
    table = collections.Counter((o.kind, o.outcome) for o in results)
    print(f"\n{len(results)} cases in {wall:.0f} s")
    head = f"| {'kind':8s} | cases | " + " | ".join(OUTCOMES) + " |"
    print(head)
    print("|" + "---|" * (2 + len(OUTCOMES)))
    for k in kinds + ["all"]:
        row = [o for o in results if k in ("all", o.kind)]
        counts = [sum(1 for o in row if o.outcome == oc) for oc in OUTCOMES]
        print(f"| {k:8s} | {len(row)} | " + " | ".join(str(c) for c in counts) + " |")
    if args.json:
        args.json.write_text(json.dumps([o.__dict__ for o in results], indent=1))


if __name__ == "__main__":
    main()
