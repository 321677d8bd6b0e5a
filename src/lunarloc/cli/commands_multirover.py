"""`lunarloc run A.lac B.lac [--reference MAP] [--share-maps] -o OUT`: several rovers on one
clock (the driver is :mod:`lunarloc.pipeline.multirover`; this module checks arguments and
prints)."""

from __future__ import annotations

from pathlib import Path

import typer

from lunarloc.cli.app import console


def run_several(
    archives: list[Path],
    reference: Path | None,
    out: Path,
    run_config,
    *,
    share_maps: bool,
    plot: bool,
    overwrite: bool,
) -> None:
    """`run_config`: the :class:`~lunarloc.config.run.RunConfig` of `lunarloc run` (``--config`` and
    the options given), used by every rover."""
    from rich.table import Table
    from tqdm import tqdm

    from lunarloc.core.errors import ConfigError
    from lunarloc.pipeline.multirover import (
        MultiRoverConfig,
        check_archives,
        rover_names,
        run_rovers,
        write_rover_outputs,
    )
    from lunarloc.io.outputs import check_output_dir
    from lunarloc.pipeline.reference import load_reference

    if len(archives) < 2:
        raise ConfigError("--share-maps needs several archives (rovers) to share maps between")
    if reference is None and not share_maps:
        raise ConfigError("several archives need --reference MAP, --share-maps, or both")
    cfg = MultiRoverConfig(run=run_config, share_maps=share_maps)
    paths = check_archives(archives, cfg)
    check_output_dir(out, overwrite, ("rovers.json", "map_all.png"), marker="rovers.json")
    for name in rover_names(paths):
        check_output_dir(out / name, overwrite)
    ref = load_reference(reference, run_config.loop.aggregation) if reference is not None else None
    with tqdm(unit="tick", desc=f"{len(paths)} rovers", dynamic_ncols=True, mininterval=1.0) as bar:

        def ticked(done: int, total: int) -> None:
            if bar.total != total:
                bar.reset(total)
            bar.update(done - bar.n)

        res = run_rovers(paths, ref, cfg, progress=ticked)
    written = write_rover_outputs(res, out, plot=plot)
    t = Table(
        title=f"{len(paths)} rovers on one clock"
        + (f" in {reference.name}" if reference else "")
        + (", sharing maps" if share_maps else "")
    )
    for col in (
        "rover",
        "path m",
        "fixes",
        "of them shared",
        "odometry RMSE m",
        "corrected RMSE m",
        "online RMSE m",
        "worst shared fix cm",
    ):
        t.add_column(col, justify="right")
    for r in res.summary()["rovers"]:
        mx = r["max_shared_fix_error_m"]
        t.add_row(
            r["name"],
            f"{r['path_length_m']:.1f}",
            str(r["fixes"]),
            str(r["shared_fixes"]),
            *(
                f"{r[k]['rmse_m']:.3f}" if k in r else "-"
                for k in ("ate_odometry", "ate_corrected", "ate_online")
            ),
            "-" if mx is None else f"{mx * 100:.1f}",
        )
    console().print(t)
    typer.echo(
        "odometry: "
        + ", ".join(f"{r.name} {r.result.config['info']['odometry_source']}" for r in res.rovers)
    )
    for p in written:
        typer.echo(f"wrote {p}")
    typer.echo(
        f"wrote {out}/<rover>/ for {', '.join(r.name for r in res.rovers)} (the layout of one "
        "`lunarloc run`; its config.json repeats it with --config)"
    )
