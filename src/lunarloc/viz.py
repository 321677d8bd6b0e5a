"""Figures of an online-localization run (matplotlib, Agg backend, imported lazily).

All figures read a run's output folder (see :func:`lunarloc.pipeline.write_outputs`), so
``lunarloc plot OUTDIR`` regenerates them without re-running anything:

* ``map.png``: top-down map (ref frame, metres): ground-truth rocks, reference landmarks,
  vehicle landmarks before (raw odometry) and after alignment (corrected poses), inlier
  association lines of accepted fixes (from the landmark's position before the fix to its
  reference landmark), trajectories (ground truth, odometry, corrected).
* ``error.png``: position error over time of odometry, online and corrected estimates,
  with the moments of accepted (and rejected) fixes.
* ``frame.png``: one camera frame with its rock detections.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from lunarloc.errors import FileFormatError

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = ["plot_run", "plot_map", "plot_error", "plot_frame"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    """savefig to a temporary name in the same folder, renamed into place."""
    from lunarloc.outputs import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp)


def _load_run(outdir: Path) -> dict:
    try:
        return _read_run(outdir)
    except (ValueError, IndexError) as exc:  # json, TUM or CSV contents; LunarLocErrors pass through
        if isinstance(exc, FileFormatError):
            raise
        raise FileFormatError(f"{outdir}: damaged run folder ({type(exc).__name__}: {str(exc)[:120]})") from None


def _read_run(outdir: Path) -> dict:
    from lunarloc.maps import load_map
    from lunarloc.pipeline import read_tum

    outdir = Path(outdir)
    need = ["trajectory.tum", "trajectory_odometry.tum", "attempts.json", "summary.json"]
    missing = [n for n in need if not (outdir / n).is_file()]
    if missing:
        raise FileFormatError(f"{outdir}: not a lunarloc run folder (missing {', '.join(missing)})")
    run: dict = {}
    run["t"], run["corrected"] = read_tum(outdir / "trajectory.tum")
    _, run["odometry"] = read_tum(outdir / "trajectory_odometry.tum")
    for name, key in (("trajectory_online.tum", "online"), ("trajectory_groundtruth.tum", "gt")):
        run[key] = read_tum(outdir / name)[1] if (outdir / name).is_file() else None
    run["attempts"] = json.loads((outdir / "attempts.json").read_text())
    run["summary"] = json.loads((outdir / "summary.json").read_text())
    for name, key in (("reference_map.csv", "ref"), ("vehicle_map.csv", "veh"), ("vehicle_map_odometry.csv", "veh_odo")):
        run[key] = load_map(outdir / name).positions_xyz if (outdir / name).is_file() else np.zeros((0, 3))
    rocks = outdir / "rocks.csv"
    run["rocks"] = np.loadtxt(rocks, delimiter=",", skiprows=1, ndmin=2) if rocks.is_file() else None
    return run


def plot_map(run: dict, path: Path, title: str = "") -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 8), dpi=100)
    if run["rocks"] is not None and len(run["rocks"]):
        r = run["rocks"]
        ax.scatter(r[:, 1], r[:, 2], s=np.clip(r[:, 4] * 120, 1, 60), c="0.75", marker="o", lw=0, label="ground-truth rocks")
    if len(run["ref"]):
        ax.scatter(run["ref"][:, 0], run["ref"][:, 1], s=22, facecolors="none", edgecolors="tab:blue", lw=0.9,
                   label="reference landmarks")  # fmt: skip
    if len(run["veh_odo"]):
        ax.scatter(run["veh_odo"][:, 0], run["veh_odo"][:, 1], s=10, c="tab:red", marker="x", lw=0.8,
                   label="vehicle landmarks, odometry (before)")  # fmt: skip
    if len(run["veh"]):
        ax.scatter(run["veh"][:, 0], run["veh"][:, 1], s=9, c="tab:green", marker="+", lw=0.9,
                   label="vehicle landmarks, corrected (after)")  # fmt: skip
    first = True
    for a in run["attempts"]:
        if not a.get("accepted") or not a.get("inlier_vehicle_xyz"):
            continue
        V = np.asarray(a["inlier_vehicle_xyz"])
        R = np.asarray(a["inlier_reference_xyz"])
        for v, q in zip(V, R):
            ax.plot([v[0], q[0]], [v[1], q[1]], c="orange", lw=0.6, alpha=0.7, label="inlier associations" if first else None)
            first = False
    if run["gt"] is not None:
        ax.plot(run["gt"][:, 0], run["gt"][:, 1], c="k", lw=1.6, label="ground truth")
    ax.plot(run["odometry"][:, 0], run["odometry"][:, 1], c="tab:red", lw=1.2, ls="--", label="odometry")
    ax.plot(run["corrected"][:, 0], run["corrected"][:, 1], c="tab:green", lw=1.2, label="corrected")
    fx = np.array([a["fix_xyz"] for a in run["attempts"] if a.get("accepted") and a.get("fix_xyz")]).reshape(-1, 3)
    if len(fx):
        ax.scatter(fx[:, 0], fx[:, 1], s=14, c="tab:green", edgecolors="k", lw=0.5, zorder=5, label="fixes")
    # frame the trajectories (plus a margin), not the whole site
    P = np.vstack([run["odometry"][:, :2], run["corrected"][:, :2]] + ([run["gt"][:, :2]] if run["gt"] is not None else []))
    _frame_square(ax, P)
    ax.set_title(title or "Online localization: top-down map")
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85, markerscale=1.2)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_error(run: dict, path: Path, title: str = "") -> Path:
    plt = _plt()
    if run["gt"] is None:
        raise FileFormatError("no ground-truth trajectory in the run folder: cannot plot the error")
    t = run["t"] - run["t"][0]
    gt = run["gt"]
    fig, ax = plt.subplots(figsize=(9, 4), dpi=100)
    for key, col, lab in (("odometry", "tab:red", "odometry"), ("online", "tab:blue", "online (causal)"),
                          ("corrected", "tab:green", "corrected (pose graph)")):  # fmt: skip
        if run.get(key) is None:
            continue
        e = np.linalg.norm(run[key][:, :3] - gt[:, :3], axis=1)
        ax.plot(t, e, c=col, lw=1.2, label=lab)
    t0 = run["t"][0]
    acc = [a["time_s"] - t0 for a in run["attempts"] if a.get("accepted")]
    rej = [a["time_s"] - t0 for a in run["attempts"] if a.get("success") and not a.get("accepted")]
    for i, x in enumerate(acc):
        ax.axvline(x, c="tab:green", lw=0.5, alpha=0.35, label="fix" if i == 0 else None)
    for i, x in enumerate(rej):
        ax.axvline(x, c="tab:orange", lw=0.8, ls=":", label="fix rejected by gate" if i == 0 else None)
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
    from lunarloc.inputs import load_npz_arrays

    z = load_npz_arrays(npz_path)  # checked before allocating; FileFormatError naming the file
    try:
        img, uv, rad, depth = z["image"], z["uv"], z["radius_px"], z["depth_m"]
        frame, cam = int(z["frame"]), str(z["camera"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(f"{npz_path}: not an example frame ({type(exc).__name__}: {exc})") from None
    h, w = img.shape[:2]
    fig, ax = plt.subplots(figsize=(9, 9 * h / w + 0.4), dpi=100)
    ax.imshow(img, cmap="gray", vmin=0, vmax=255)
    from matplotlib.patches import Circle

    for (u, v), r, d in zip(uv, rad, depth):
        ax.add_patch(Circle((u, v), max(float(r), 3.0), fill=False, ec="lime", lw=1.2))
        ax.text(u + max(r, 3) + 2, v, f"{d:.1f} m", color="yellow", fontsize=7, va="center")
    ax.set_axis_off()
    ax.set_title(f"{cam}, frame {frame}: {len(uv)} rock detections (circle: estimated radius)", fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_run(outdir: str | Path, figdir: str | Path | None = None) -> list[Path]:
    """Write map.png, error.png (if ground truth is known) and frame.png (if the run used
    images) for the run in `outdir` into `figdir` (default: `outdir`). Returns the paths."""
    outdir = Path(outdir)
    figdir = Path(figdir) if figdir is not None else outdir
    figdir.mkdir(parents=True, exist_ok=True)
    run = _load_run(outdir)
    s = run["summary"]
    title = f"{Path(str(s.get('source', ''))).name}: {s.get('fixes', 0)} fixes over {s.get('path_length_m', 0):.0f} m"
    out = [plot_map(run, figdir / "map.png", title)]
    if run["gt"] is not None:
        out.append(plot_error(run, figdir / "error.png"))
    if (outdir / "example_frame.npz").is_file():
        out.append(plot_frame(outdir / "example_frame.npz", figdir / "frame.png"))
    return out


def plot_rovers(outdirs: list[str | Path], path: str | Path, names: list[str] | None = None, title: str = "") -> Path:
    """One top-down map of several rovers' run folders (``lunarloc run A.lac B.lac``): per
    rover (one colour each) ground truth (thin black-edged), odometry (dotted), corrected
    (solid), its landmarks (+) and accepted fixes; ground-truth rocks and the reference in grey."""
    plt = _plt()
    runs = [_load_run(Path(d)) for d in outdirs]
    names = names or [Path(d).name for d in outdirs]
    fig, ax = plt.subplots(figsize=(9, 9), dpi=100)
    rocks = next((r["rocks"] for r in runs if r["rocks"] is not None and len(r["rocks"])), None)
    if rocks is not None:
        ax.scatter(rocks[:, 1], rocks[:, 2], s=np.clip(rocks[:, 4] * 120, 1, 60), c="0.8", lw=0, label="ground-truth rocks")
    if len(runs[0]["ref"]):
        ax.scatter(runs[0]["ref"][:, 0], runs[0]["ref"][:, 1], s=20, facecolors="none", edgecolors="0.45", lw=0.8,
                   label="reference landmarks")  # fmt: skip
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    pts = []
    for i, (run, name) in enumerate(zip(runs, names)):
        c = colors[i % len(colors)]
        s = run["summary"]
        lab = name
        if "ate_corrected" in s:
            lab += f" (RMSE odometry {s['ate_odometry']['rmse_m'] * 100:.1f} cm, corrected {s['ate_corrected']['rmse_m'] * 100:.1f} cm)"
        if run["gt"] is not None:
            ax.plot(run["gt"][:, 0], run["gt"][:, 1], c="k", lw=2.6, alpha=0.35)
            pts.append(run["gt"][:, :2])
        ax.plot(run["odometry"][:, 0], run["odometry"][:, 1], c=c, lw=1.0, ls=":")
        ax.plot(run["corrected"][:, 0], run["corrected"][:, 1], c=c, lw=1.4, label=lab)
        if len(run["veh"]):
            ax.scatter(run["veh"][:, 0], run["veh"][:, 1], s=10, color=c, marker="+", lw=0.8)
        fx = np.array([a["fix_xyz"] for a in run["attempts"] if a.get("accepted") and a.get("fix_xyz")]).reshape(-1, 3)
        if len(fx):
            ax.scatter(fx[:, 0], fx[:, 1], s=16, color=c, edgecolors="k", lw=0.5, zorder=5)
        pts += [run["odometry"][:, :2], run["corrected"][:, :2]]
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
