"""`lunarloc campaign`: a grid of scenarios as Dask tasks."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lunarloc.cli.app import app, console


@app.command("campaign")
def campaign_cmd(
    spec: Optional[Path] = typer.Argument(None, help="Campaign spec (TOML); see --example."),
    out: Optional[Path] = typer.Option(
        None, "-o", "--out", help="Output folder (jobs/, results.csv, summary.png)."
    ),
    scheduler: Optional[str] = typer.Option(
        None,
        "--scheduler",
        help="Dask scheduler address (tcp://host:8786); 'sync' runs the jobs one after another "
        "here; default: a local cluster.",
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", min=1, max=256, help="Local cluster workers (default: cores)."
    ),
    example: bool = typer.Option(
        False, "--example", help="Print a small valid spec (8 jobs) and exit."
    ),
) -> None:
    """Run a grid of simulate -> map -> run -> score jobs (site seeds x sun x rock density ...)
    on Dask; failed jobs are reported, finished ones skipped on a rerun. Exit 1 when a job
    failed (raised) or did not pass its check."""
    from lunarloc.pipeline.campaign import EXAMPLE_SPEC, load_spec, run_campaign

    if example:
        typer.echo(EXAMPLE_SPEC, nl=False)
        return
    if spec is None or out is None:
        raise typer.BadParameter("give SPEC and -o OUT (or --example to print a spec)")
    if scheduler is not None and workers is not None:
        raise typer.BadParameter(
            "--workers sizes the local cluster; it does not go with --scheduler"
        )
    if scheduler not in (None, "sync"):
        from lunarloc.pipeline.campaign import check_scheduler_address

        check_scheduler_address(scheduler)  # before anything is printed or written
    s = load_spec(spec)
    jobs = s.jobs()
    con = console()
    con.print(f"campaign '{s.name}': {len(jobs)} jobs into {out}/")

    from rich.progress import Progress

    with Progress(console=con, transient=True) as prog:
        task = prog.add_task("jobs", total=len(jobs))

        def on_done(row, done, total):
            prog.update(task, completed=done, description=f"{row['job']}: {row['status']}")
            if row["status"] != "ok":
                con.print(f"[red]{row['job']}: {row['status']}[/red] {row.get('error', '')}")
            elif row.get("check") != "pass":
                con.print(f"[yellow]{row['job']}: check: {row.get('check')}[/yellow]")

        res = run_campaign(s, out, scheduler=scheduler, workers=workers, progress=on_done)

    from rich.table import Table

    t = Table(title=f"campaign '{s.name}' ({res.scheduler})")
    for col in (
        "job",
        "status",
        "check",
        "ref lm",
        "fixes",
        "odo RMSE cm",
        "corr RMSE cm",
        "wall s",
    ):
        t.add_column(col, justify="left" if col in ("job", "status") else "right")

    def cm(v):
        return "-" if v in (None, "") else f"{float(v) * 100:.1f}"

    for r in res.rows:
        chk = r.get("check", "")
        t.add_row(
            r["job"],
            r["status"] if r["status"] == "ok" else f"[red]{r['status']}[/red]",
            chk if chk in ("pass", "") else f"[yellow]{chk}[/yellow]",
            str(r.get("reference_landmarks", "-")),
            str(r.get("fixes", "-")),
            cm(r.get("odometry_rmse_m")),
            cm(r.get("corrected_rmse_m")),
            f"{r.get('wall_s', 0):.0f}",
        )
    con.print(t)
    counts = ", ".join(f"{v} {k}" for k, v in sorted(res.counts.items()))
    counts += f", {sum(r.get('check') == 'pass' for r in res.rows)} passed the check"
    con.print(
        f"{len(res.rows)} jobs ({counts}; {res.skipped} finished earlier, skipped) in "
        f"{res.wall_s:.0f} s wall"
    )
    con.print(f"wrote {res.table_csv}" + (f" and {res.figure}" if res.figure else ""))
    if any(r["status"] != "ok" or r.get("check") != "pass" for r in res.rows):
        raise typer.Exit(1)
