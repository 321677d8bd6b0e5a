"""`lunarloc info`: summarise a `.lac` archive and optionally plot its trajectory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from lunarloc.cli.app import app, console
from lunarloc.cli.checks import OVERWRITE_OPT

PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")


def _summary(archive) -> dict:
    cams = []
    for name, cfg in archive.configured_cameras.items():
        cams.append(
            {
                "name": name,
                "active": bool(cfg.get("camera_active", False)),
                "size": f"{cfg.get('width', '?')}x{cfg.get('height', '?')}",
                "rows": archive.camera_frames(name).n_rows,
                "grayscale": archive.image_count(name, "grayscale"),
                "semantic": archive.image_count(name, "semantic"),
            }
        )
    customs = []
    for rec in archive.custom_records:
        t = archive.custom(rec)
        customs.append({"name": rec, "rows": t.n_rows, "columns": t.columns})
    return {
        "frames": archive.n_frames,
        "first_frame": int(archive.frame_numbers[0]) if archive.n_frames else None,
        "last_frame": int(archive.frame_numbers[-1]) if archive.n_frames else None,
        "duration_s": archive.duration(),
        "path_length_m": archive.path_length(),
        "cameras": cams,
        "custom": customs,
    }


def _plot(archive, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    fig, ax = plt.subplots(figsize=(7, 7))
    xy = [archive.positions()[:, :2]]
    if "rocks" in archive.custom_records:
        rocks = archive.custom("rocks")
        if all(c in rocks for c in ("x", "y", "radius")):
            circles = [
                Circle((x, y), r) for x, y, r in zip(rocks["x"], rocks["y"], rocks["radius"])
            ]
            ax.add_collection(
                PatchCollection(circles, facecolor="0.55", edgecolor="0.3", linewidth=0.3)
            )
            r = rocks["radius"][:, None]
            xy += [
                np.stack([rocks["x"], rocks["y"]], axis=1) - r,
                np.stack([rocks["x"], rocks["y"]], axis=1) + r,
            ]
            ax.plot([], [], "o", color="0.55", label=f"rocks ({rocks.n_rows})")
    p = archive.positions()
    if len(p):
        ax.plot(p[:, 0], p[:, 1], "-", color="tab:blue", lw=1.5, label="ground truth")
        ax.plot(p[0, 0], p[0, 1], "o", color="tab:green", label="start")
        ax.plot(p[-1, 0], p[-1, 1], "s", color="tab:red", label="end")
    if "odometry" in archive.custom_records:
        odo = archive.custom("odometry")
        if "x" in odo and "y" in odo:
            ax.plot(odo["x"], odo["y"], "--", color="tab:orange", lw=1.0, label="odometry")
    lander = archive.lander_pose_map()  # initial.toml's lander is rover-relative
    ax.plot(lander[0], lander[1], "^", color="k", ms=9, label="lander")
    xy.append(np.array([lander[:2]]))
    pts = np.concatenate([p for p in xy if len(p)]) if any(len(p) for p in xy) else np.zeros((1, 2))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.05 * max(float(np.max(hi - lo)), 1.0)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(archive.path.name)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.grid(alpha=0.3)
    from lunarloc.io.outputs import atomic_path

    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)


@app.command("info")
def info(
    archive_path: Path = typer.Argument(..., help="A .lac archive."),
    plot: Path | None = typer.Option(
        None, "--plot", help="Write a top-down plot of the trajectory (and rocks) to this PNG."
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Summarise a .lac archive: frames, duration, cameras, image counts, path length, custom
    records."""
    from rich.table import Table as RichTable

    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.core.errors import ConfigError
    from lunarloc.io.outputs import check_output_file

    if plot is not None:
        if plot.suffix.lower() not in PLOT_SUFFIXES:
            raise ConfigError(
                f"--plot {plot}: unknown image format {plot.suffix!r} (use "
                f"{', '.join(PLOT_SUFFIXES)})"
            )
        check_output_file(plot, overwrite, "plot")

    con = console()
    with LacArchive(archive_path) as archive:
        s = _summary(archive)
        md = archive.metadata
        con.print(f"[bold]{archive_path}[/bold]")
        if md.get("description"):
            con.print(f"  description : {md['description']}")
        con.print(
            f"  data_spec   : {md.get('data_spec', '?')}   recorded {md.get('start_time', '?')} .. "
            f"{md.get('end_time', '?')}"
        )
        frames = s["frames"]
        span = f" ({s['first_frame']}..{s['last_frame']})" if frames else ""
        con.print(f"  frames      : {frames}{span}")
        con.print(f"  duration    : {s['duration_s']:.2f} s")
        con.print(f"  path length : {s['path_length_m']:.2f} m")
        cam_table = RichTable(title="cameras", show_edge=False)
        for col in ("camera", "active", "size", "rows", "grayscale", "semantic"):
            cam_table.add_column(col, justify="left" if col == "camera" else "right")
        for c in s["cameras"]:
            cam_table.add_row(
                c["name"],
                "yes" if c["active"] else "no",
                c["size"],
                str(c["rows"]),
                str(c["grayscale"]),
                str(c["semantic"]),
            )
        con.print(cam_table)
        if s["custom"]:
            rec_table = RichTable(title="custom records", show_edge=False)
            rec_table.add_column("record")
            rec_table.add_column("rows", justify="right")
            rec_table.add_column("columns")
            for r in s["custom"]:
                rec_table.add_row(r["name"], str(r["rows"]), ",".join(r["columns"]))
            con.print(rec_table)
        else:
            con.print("  custom records: none")
        if plot is not None:
            _plot(archive, plot)
            con.print(f"plot written to {plot}")
