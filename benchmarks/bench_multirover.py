"""Several rovers on one clock: each rover's RMSE against ground truth with shared maps and no
reference, with the reference alone, and with both, against its own odometry.

    python benchmarks/bench_multirover.py --data DIR [--traverses 0 1] [--odometry visual]
        [--config RUN_CONFIG.json] [--modes share ref ref+share ref0+share] [--out OUT]

DIR holds a simulated site (``rocks.csv``, ``traverse_<i>.lac``), e.g. from
``simulate_dataset(3, 3, DIR, SimulationConfig(site=SiteConfig(n_rocks=800), duration_s=240,
width=640, height=360, cameras=("FrontLeft", "FrontRight"), semantic=False))``. The reference
is the ground-truth rock list (``rocks.csv``). Prints a markdown table; with ``--out`` also
writes each mode's run folders and ``bench.json``. CPU time is process time (the machine may be
shared).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--traverses", type=int, nargs="+", default=[0, 1])
    ap.add_argument(
        "--odometry", default=None, help="odometry source (default: the config's, else visual)"
    )
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="every rover's RunConfig (a run folder's config.json)",
    )
    ap.add_argument(
        "--modes",
        nargs="+",
        default=["share", "ref", "ref+share"],
        choices=["share", "ref", "ref+share", "ref0+share"],
        help="ref0+share: only the first rover has the reference",
    )
    ap.add_argument(
        "--max-shared-sigma-ratio",
        type=float,
        default=None,
        help="MultiRoverConfig.max_shared_sigma_ratio",
    )
    ap.add_argument(
        "--shared-bounds",
        default=None,
        choices=["sum", "rss", "own"],
        help="MultiRoverConfig.shared_bounds",
    )
    ap.add_argument(
        "--sigma-model",
        default=None,
        choices=["windows", "source", "gate"],
        help="MultiRoverConfig.sigma_model",
    )
    ap.add_argument(
        "--shared-fusion",
        default=None,
        choices=["split", "one-way"],
        help="MultiRoverConfig.shared_fusion",
    )
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()

    from lunarloc.config.run import RunConfig, load_config_file
    from lunarloc.pipeline.multirover import MultiRoverConfig, run_rovers, write_rover_outputs
    from lunarloc.pipeline.reference import load_reference

    run_cfg = load_config_file(a.config)[0] if a.config is not None else RunConfig()
    run_cfg = run_cfg.with_options(odometry__source=a.odometry)

    archives = [a.data / f"traverse_{i}.lac" for i in a.traverses]
    rows: dict[str, dict] = {}
    for mode in a.modes:
        ref = load_reference(a.data / "rocks.csv") if mode.startswith("ref") else None
        if mode == "ref0+share":
            ref = [ref] + [None] * (len(archives) - 1)
        t0, c0 = time.perf_counter(), time.process_time()
        cfg = MultiRoverConfig(run=run_cfg, share_maps="share" in mode)
        if a.max_shared_sigma_ratio is not None:
            cfg = replace(cfg, max_shared_sigma_ratio=a.max_shared_sigma_ratio)
        if a.sigma_model is not None:
            cfg = replace(cfg, sigma_model=a.sigma_model)
        if a.shared_fusion is not None:
            cfg = replace(cfg, shared_fusion=a.shared_fusion)
        if a.shared_bounds is not None:
            cfg = replace(cfg, shared_bounds=a.shared_bounds)
        res = run_rovers(archives, ref, cfg)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if a.out is not None:
            write_rover_outputs(res, a.out / mode.replace("+", "_"), plot=True)
        s = res.summary()
        for r in s["rovers"]:
            row = rows.setdefault(
                r["name"],
                {
                    "path_m": r["path_length_m"],
                    "odometry_rmse_m": r["ate_odometry"]["rmse_m"],
                    "odometry_final_m": r["final_error_odometry_m"],
                },
            )
            row[mode] = {
                "rmse_m": r["ate_corrected"]["rmse_m"],
                "online_rmse_m": r["ate_online"]["rmse_m"],
                "max_m": r["ate_corrected"]["max_m"],
                "final_m": r["final_error_corrected_m"],
                "fixes": r["fixes"],
                "shared_fixes": r["shared_fixes"],
                "worst_shared_fix_m": r["max_shared_fix_error_m"],
                "worst_shared_fix_sigmas": r["max_shared_fix_error_sigmas"],
            }
        rows.setdefault("_time", {})[mode] = {"wall_s": round(wall, 1), "cpu_s": round(cpu, 1)}
        print(f"{mode}: {wall:.0f} s wall, {cpu:.0f} s CPU", flush=True)
    head = (
        "| rover | path m | odometry RMSE / final cm | "
        + " | ".join(
            f"{m}: corrected (online) RMSE / final cm, fixes (shared), worst shared fix cm (in its sigmas)"
            for m in a.modes
        )
        + " |"
    )
    print(head)
    print("|" + "---|" * (3 + len(a.modes)))
    for name, row in rows.items():
        if name.startswith("_"):
            continue
        cells = []
        for m in a.modes:
            c = row[m]
            w = (
                "-"
                if c["worst_shared_fix_m"] is None
                else f"{100 * c['worst_shared_fix_m']:.1f} ({c['worst_shared_fix_sigmas']:.2f} sigma)"
            )
            cells.append(
                f"{100 * c['rmse_m']:.1f} ({100 * c['online_rmse_m']:.1f}) / {100 * c['final_m']:.1f}, "
                f"{c['fixes']} ({c['shared_fixes']}), {w}"
            )
        print(
            f"| {name} | {row['path_m']:.1f} | {100 * row['odometry_rmse_m']:.1f} / "
            f"{100 * row['odometry_final_m']:.1f} | " + " | ".join(cells) + " |"
        )
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "bench.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
