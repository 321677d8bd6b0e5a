"""Figures of an online-localization run (matplotlib, Agg backend, imported lazily).

All figures read a run's output folder (see :mod:`lunarloc.io.runs`), so
``lunarloc plot OUTDIR`` regenerates them without re-running anything:

* ``map.png``: top-down map (``map`` frame, metres): ground-truth rocks, reference landmarks,
  vehicle landmarks before (raw odometry) and after alignment (corrected poses), inlier
  association lines of accepted fixes (from the landmark's position before the fix to its
  reference landmark), trajectories (ground truth, odometry, corrected).
* ``error.png``: position error over time of odometry, online and corrected estimates,
  with the moments of accepted (and rejected) fixes.
* ``frame.png``: one camera frame with its rock detections.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lunarloc.core.errors import FileFormatError

if TYPE_CHECKING:
    from lunarloc.io.runs import RunFolder

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = ["plot_run", "plot_map", "plot_error", "plot_frame", "plot_lac_maps"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    """savefig to a temporary name in the same folder, renamed into place."""
    from lunarloc.io.outputs import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp)


def plot_map(run: RunFolder, path: Path, title: str = "") -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 8), dpi=100)
    if run.rocks is not None and len(run.rocks):
        r = run.rocks
        ax.scatter(
            r[:, 1],
            r[:, 2],
            s=np.clip(r[:, 4] * 120, 1, 60),
            c="0.75",
            marker="o",
            lw=0,
            label="ground-truth rocks",
        )
    if len(run.reference_xyz):
        ax.scatter(
            run.reference_xyz[:, 0],
            run.reference_xyz[:, 1],
            s=22,
            facecolors="none",
            edgecolors="tab:blue",
            lw=0.9,
            label="reference landmarks",
        )
    if len(run.vehicle_odometry_xyz):
        ax.scatter(
            run.vehicle_odometry_xyz[:, 0],
            run.vehicle_odometry_xyz[:, 1],
            s=10,
            c="tab:red",
            marker="x",
            lw=0.8,
            label="vehicle landmarks, odometry (before)",
        )
    if len(run.vehicle_xyz):
        ax.scatter(
            run.vehicle_xyz[:, 0],
            run.vehicle_xyz[:, 1],
            s=9,
            c="tab:green",
            marker="+",
            lw=0.9,
            label="vehicle landmarks, corrected (after)",
        )
    first = True
    for a in run.attempts:
        if not a.get("accepted") or not a.get("inlier_vehicle_xyz"):
            continue
        V = np.asarray(a["inlier_vehicle_xyz"])
        R = np.asarray(a["inlier_reference_xyz"])
        for v, q in zip(V, R):
            ax.plot(
                [v[0], q[0]],
                [v[1], q[1]],
                c="orange",
                lw=0.6,
                alpha=0.7,
                label="inlier associations" if first else None,
            )
            first = False
    if run.ground_truth is not None:
        ax.plot(run.ground_truth[:, 0], run.ground_truth[:, 1], c="k", lw=1.6, label="ground truth")
    ax.plot(run.odometry[:, 0], run.odometry[:, 1], c="tab:red", lw=1.2, ls="--", label="odometry")
    ax.plot(run.corrected[:, 0], run.corrected[:, 1], c="tab:green", lw=1.2, label="corrected")
    fx = np.array(
        [a["fix_xyz"] for a in run.attempts if a.get("accepted") and a.get("fix_xyz")]
    ).reshape(-1, 3)
    if len(fx):
        ax.scatter(
            fx[:, 0], fx[:, 1], s=14, c="tab:green", edgecolors="k", lw=0.5, zorder=5, label="fixes"
        )
    # frame the trajectories (plus a margin), not the whole site
    P = np.vstack(
        [run.odometry[:, :2], run.corrected[:, :2]]
        + ([run.ground_truth[:, :2]] if run.ground_truth is not None else [])
    )
    _frame_square(ax, P)
    ax.set_title(title or "Online localization: top-down map")
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85, markerscale=1.2)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_error(run: RunFolder, path: Path, title: str = "") -> Path:
    plt = _plt()
    if run.ground_truth is None:
        raise FileFormatError("no ground-truth trajectory in the run folder: cannot plot the error")
    t = run.times - run.times[0]
    gt = run.ground_truth
    fig, ax = plt.subplots(figsize=(9, 4), dpi=100)
    for key, col, lab in (
        ("odometry", "tab:red", "odometry"),
        ("online", "tab:blue", "online (causal)"),
        ("corrected", "tab:green", "corrected (pose graph)"),
    ):
        if getattr(run, key) is None:
            continue
        e = np.linalg.norm(getattr(run, key)[:, :3] - gt[:, :3], axis=1)
        ax.plot(t, e, c=col, lw=1.2, label=lab)
    t0 = run.times[0]
    acc = [a["time_s"] - t0 for a in run.attempts if a.get("accepted")]
    rej = [a["time_s"] - t0 for a in run.attempts if a.get("success") and not a.get("accepted")]
    for i, x in enumerate(acc):
        ax.axvline(x, c="tab:green", lw=0.5, alpha=0.35, label="fix" if i == 0 else None)
    for i, x in enumerate(rej):
        ax.axvline(
            x, c="tab:orange", lw=0.8, ls=":", label="fix rejected by gate" if i == 0 else None
        )
    ax.set_yscale("log")
    ax.set_ylim(1e-3, None)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position error (m)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title or "Position error vs ground truth")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_frame(npz_path: Path, path: Path) -> Path:
    plt = _plt()
    from lunarloc.io.inputs import load_npz_arrays

    z = load_npz_arrays(npz_path)  # checked before allocating; FileFormatError naming the file
    try:
        img, uv, rad, depth = z["image"], z["uv"], z["radius_px"], z["depth_m"]
        frame, cam = int(z["frame"]), str(z["camera"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(
            f"{npz_path}: not an example frame ({type(exc).__name__}: {exc})"
        ) from None
    h, w = img.shape[:2]
    fig, ax = plt.subplots(figsize=(9, 9 * h / w + 0.4), dpi=100)
    ax.imshow(img, cmap="gray", vmin=0, vmax=255)
    from matplotlib.patches import Circle

    for (u, v), r, d in zip(uv, rad, depth):
        ax.add_patch(Circle((u, v), max(float(r), 3.0), fill=False, ec="lime", lw=1.2))
        ax.text(u + max(r, 3) + 2, v, f"{d:.1f} m", color="yellow", fontsize=7, va="center")
    ax.set_axis_off()
    ax.set_title(
        f"{cam}, frame {frame}: {len(uv)} rock detections (circle: estimated radius)", fontsize=9
    )
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_run(
    outdir: str | Path, figdir: str | Path | None = None, summary: dict | None = None
) -> list[Path]:
    """Write map.png, error.png (if ground truth is known) and frame.png (if the run used
    images) for the run in `outdir` into `figdir` (default: `outdir`). Returns the paths.
    `summary`: the run's summary before ``summary.json`` is written (``write_run``'s
    ``before_summary``: figures first, the file marking a complete run last)."""
    outdir = Path(outdir)
    figdir = Path(figdir) if figdir is not None else outdir
    figdir.mkdir(parents=True, exist_ok=True)
    from lunarloc.io.runs import read_run

    run = read_run(outdir, summary)
    s = run.summary
    source = Path(str(s.get("source", ""))).name
    title = f"{source}: {s.get('fixes', 0)} fixes over {s.get('path_length_m', 0):.0f} m"
    out = [plot_map(run, figdir / "map.png", title)]
    if run.ground_truth is not None:
        out.append(plot_error(run, figdir / "error.png"))
    if (outdir / "example_frame.npz").is_file():
        out.append(plot_frame(outdir / "example_frame.npz", figdir / "frame.png"))
    return out


def plot_rovers(
    outdirs: list[str | Path], path: str | Path, names: list[str] | None = None, title: str = ""
) -> Path:
    """One top-down map of several rovers' run folders (``lunarloc run A.lac B.lac``): per
    rover (one colour each) ground truth (thin black-edged), odometry (dotted), corrected
    (solid), its landmarks (+) and accepted fixes; ground-truth rocks and the reference in grey."""
    from lunarloc.io.runs import read_run

    plt = _plt()
    runs = [read_run(d) for d in outdirs]
    names = names or [Path(d).name for d in outdirs]
    fig, ax = plt.subplots(figsize=(9, 9), dpi=100)
    rocks = next((r.rocks for r in runs if r.rocks is not None and len(r.rocks)), None)
    if rocks is not None:
        ax.scatter(
            rocks[:, 1],
            rocks[:, 2],
            s=np.clip(rocks[:, 4] * 120, 1, 60),
            c="0.8",
            lw=0,
            label="ground-truth rocks",
        )
    if len(runs[0].reference_xyz):
        ax.scatter(
            runs[0].reference_xyz[:, 0],
            runs[0].reference_xyz[:, 1],
            s=20,
            facecolors="none",
            edgecolors="0.45",
            lw=0.8,
            label="reference landmarks",
        )
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    pts = []
    for i, (run, name) in enumerate(zip(runs, names)):
        c = colors[i % len(colors)]
        s = run.summary
        lab = name
        if "ate_corrected" in s:
            odo_cm = s["ate_odometry"]["rmse_m"] * 100
            corrected_cm = s["ate_corrected"]["rmse_m"] * 100
            lab += f" (RMSE odometry {odo_cm:.1f} cm, corrected {corrected_cm:.1f} cm)"
        if run.ground_truth is not None:
            ax.plot(run.ground_truth[:, 0], run.ground_truth[:, 1], c="k", lw=2.6, alpha=0.35)
            pts.append(run.ground_truth[:, :2])
        ax.plot(run.odometry[:, 0], run.odometry[:, 1], c=c, lw=1.0, ls=":")
        ax.plot(run.corrected[:, 0], run.corrected[:, 1], c=c, lw=1.4, label=lab)
        if len(run.vehicle_xyz):
            ax.scatter(
                run.vehicle_xyz[:, 0], run.vehicle_xyz[:, 1], s=10, color=c, marker="+", lw=0.8
            )
        fx = np.array(
            [a["fix_xyz"] for a in run.attempts if a.get("accepted") and a.get("fix_xyz")]
        ).reshape(-1, 3)
        if len(fx):
            ax.scatter(fx[:, 0], fx[:, 1], s=16, color=c, edgecolors="k", lw=0.5, zorder=5)
        pts += [run.odometry[:, :2], run.corrected[:, :2]]
    ax.plot([], [], c="k", lw=2.6, alpha=0.35, label="ground truth")
    ax.plot([], [], c="0.3", lw=1.0, ls=":", label="odometry")
    ax.scatter([], [], s=10, c="0.3", marker="+", label="rover landmarks (corrected)")
    ax.scatter([], [], s=16, c="0.3", edgecolors="k", lw=0.5, label="accepted fixes")
    P = np.vstack(pts)
    _frame_square(ax, P)
    ax.set_title(title or f"{len(runs)} rovers on one clock: ground truth, odometry and corrected")
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
    fig.tight_layout()
    path = Path(path)
    _save(fig, path)
    plt.close(fig)
    return path


def _frame_square(ax, P: np.ndarray, margin_m: float = 3.0) -> None:
    """Square, equal-aspect axes around the points P (N, 2) plus a margin; labelled, gridded."""
    lo, hi = P.min(axis=0) - margin_m, P.max(axis=0) + margin_m
    c, h = (lo + hi) / 2, max(hi - lo) / 2
    ax.set_xlim(c[0] - h, c[0] + h)
    ax.set_ylim(c[1] - h, c[1] + h)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)


def plot_lac_maps(
    produced: np.ndarray,
    truth: np.ndarray,
    path: str | Path,
    observed: np.ndarray | None = None,
    height_tolerance_m: float = 0.05,
    title: str = "",
) -> Path:
    """Produced LAC map, true map and per-cell error side by side (site frame, metres; x to
    the right, y up): heights with rock cells outlined, the height error (cells beyond the
    tolerance hatched by colour saturation, unfilled cells black) and the rock flags (true
    positives green, false positives red, misses blue). `observed` (N, N) bool outlines the
    cells the cameras saw on the error panel."""
    plt = _plt()
    from matplotlib.colors import ListedColormap

    p, t = np.asarray(produced, float), np.asarray(truth, float)
    cell = float(abs(t[1, 0, 0] - t[0, 0, 0]))
    ext = [
        t[0, 0, 0] - cell / 2,
        t[-1, 0, 0] + cell / 2,
        t[0, 0, 1] - cell / 2,
        t[0, -1, 1] + cell / 2,
    ]
    ph = np.where(np.isfinite(p[:, :, 2]), p[:, :, 2], np.nan)
    lo, hi = np.nanpercentile(t[:, :, 2], [1, 99])
    fig, axes = plt.subplots(1, 4, figsize=(22, 5.8), dpi=90)
    show = dict(origin="lower", extent=ext, interpolation="nearest")
    for ax, h, name in (
        (axes[0], ph, "produced height"),
        (axes[1], t[:, :, 2], "true height (16-ray mean)"),
    ):
        im = ax.imshow(h.T, cmap="gist_earth", vmin=lo, vmax=hi, **show)
        ax.set_title(name)
        fig.colorbar(im, ax=ax, fraction=0.046, label="m")
    err = ph - t[:, :, 2]
    ok = np.abs(err) < height_tolerance_m
    im = axes[2].imshow(np.clip(err, -0.2, 0.2).T, cmap="coolwarm", vmin=-0.2, vmax=0.2, **show)
    axes[2].imshow(
        np.where(np.isfinite(err), np.nan, 1.0).T, cmap=ListedColormap(["black"]), **show
    )
    fig.colorbar(im, ax=axes[2], fraction=0.046, label="produced - true (m)")
    share = (
        float(np.mean(ok[observed]))
        if observed is not None and observed.any()
        else float(np.mean(ok))
    )
    where = "seen cells" if observed is not None else "all cells"
    axes[2].set_title(
        f"height error: {share:.1%} of {where} within {height_tolerance_m * 100:g} cm"
    )
    if observed is not None:
        axes[2].contour(
            np.arange(t.shape[0]) * cell + ext[0] + cell / 2,
            np.arange(t.shape[1]) * cell + ext[2] + cell / 2,
            observed.T.astype(float),
            levels=[0.5],
            colors="k",
            linewidths=0.6,
        )
    pr, tr = p[:, :, 3] >= 0.5, t[:, :, 3] >= 0.5
    code = np.zeros(pr.shape)
    code[pr & tr], code[pr & ~tr], code[~pr & tr] = 1, 2, 3
    cmap = ListedColormap(["white", "tab:green", "tab:red", "tab:blue"])
    axes[3].imshow(code.T, cmap=cmap, vmin=-0.5, vmax=3.5, **show)
    tp, fp, fn = int((code == 1).sum()), int((code == 2).sum()), int((code == 3).sum())
    f1 = 2 * tp / (2 * tp + fp + fn) if tp else 0.0
    axes[3].set_title(
        f"rock cells: F1 {f1:.2f}\n{tp} right (green), {fp} false (red), {fn} missed (blue)"
    )
    for ax in axes:
        ax.set_xlabel("x (m)")
        ax.set_aspect("equal")
    axes[0].set_ylabel("y (m)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    _save(fig, path)
    plt.close(fig)
    return path
