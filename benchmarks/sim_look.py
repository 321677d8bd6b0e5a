"""Figure: real LAC frames beside LAC-look simulated frames (``SiteConfig.lac_style()``), all
with the detector's detections drawn.

    python benchmarks/sim_look.py [--real ../shared/data/lac-real] [--seed 300] [--[no-]small-rocks]
        [--out docs/images/lac_vs_sim_style.png]

Panels: top, the real frames FrontLeft 99 (lit, the lander, the rover's shadow; its
ground-truth pose) and ipex 185 (the rover tilted on a crater rim; no pose, so the rover
frame is the detector's only frame); bottom, two frames of a LAC-look site (seed `--seed`,
traverse 0): the frame of the traverse whose rover tilt is largest and the frame whose
tilt is the median, sun ``sun_of(seed)`` of ``sim_heldout.py``. Detections: the detector's
overlay (kept masks green with a cross, rejected masks coloured by filter), default
settings or ``--[no-]small-rocks``. In the simulated panels the true rocks within 6 m are
outlined: yellow r >= 0.1 m, cyan 0.025-0.1 m; a miss is an outline without a cross.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _overlay(det, left, right, T_ro, T_map_rover, lander_xy):
    from lunarloc.perception.detector import debug_overlay

    pr = det.detect_pair(left, right, T_ro, T_map_rover, "FrontLeft", lander_xy=lander_xy)
    print(
        f"  {len(pr.detections)} detections: "
        + ", ".join(f"{d.depth_m:.1f} m r {d.radius_m:.2f}" for d in pr.detections)
    )
    return debug_overlay(left, pr)[:, : left.shape[1], ::-1].copy()


def _outline(img, sem, site, cam_xyz, max_range=6.0):
    import cv2

    from lunarloc.sim.render import semantic_to_rock_id

    ids = semantic_to_rock_id(sem)
    for rid in np.unique(ids[ids >= 0]):
        k = int(rid)
        r = float(site.rocks.radii[k])
        if r < 0.025 or np.linalg.norm(site.rocks.centers[k] - cam_xyz) > max_range:
            continue
        contours, _ = cv2.findContours(
            (ids == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
        )
        cv2.drawContours(img, contours, -1, (255, 255, 0) if r >= 0.1 else (0, 255, 255), 1)
    return img


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--real", type=Path, default=Path("../shared/data/lac-real"))
    ap.add_argument("--seed", type=int, default=300)
    ap.add_argument("--small-rocks", action=argparse.BooleanOptionalAction, default=None)
    ap.add_argument("--out", type=Path, default=Path("docs/images/lac_vs_sim_style.png"))
    a = ap.parse_args(argv)
    import json

    from PIL import Image
    from sim_heldout import sun_of

    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import Detector, DetectorConfig
    from lunarloc.sim.render import RenderConfig, SiteRenderer
    from lunarloc.sim.rover import plan_traverse
    from lunarloc.sim.simulate import traverse_seed
    from lunarloc.sim.site import SiteConfig, generate_site

    def load(name):
        p = a.real / name
        if not p.exists():
            raise SystemExit(f"{p} not found: the real LAC frames are needed")
        return np.asarray(Image.open(p).convert("L"))

    camera = PinholeCamera(1280, 720)
    rig = ipex_rig(camera)
    T_ro = rig["FrontLeft"].T_rover_optical
    cfg = DetectorConfig()
    if a.small_rocks is not None:
        cfg = replace(cfg, small_rocks=replace(cfg.small_rocks, enabled=a.small_rocks))
    det = Detector(cfg, camera)
    panels = []
    pose = json.loads((a.real / "pose_99.json").read_text())
    T99 = pose_to_matrix(*[float(pose[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")])
    print("real FrontLeft 99")
    panels.append(
        (
            "real LAC, FrontLeft 99",
            _overlay(
                det, load("FrontLeft_99.png"), load("FrontRight_99.png"), T_ro, T99, np.zeros(2)
            ),
        )
    )
    print("real ipex 185")
    panels.append(
        (
            "real LAC, ipex 185 (tilted on a crater rim)",
            _overlay(
                det,
                load("ipex/FrontLeft_1_185.png"),
                load("ipex/FrontRight_1_185.png"),
                T_ro,
                None,
                None,
            ),
        )
    )
    site = generate_site(a.seed, SiteConfig.lac_style())
    el, az = sun_of(a.seed)
    renderer = SiteRenderer(site, RenderConfig.lac_style(sun_elevation_deg=el, sun_azimuth_deg=az))
    tr = plan_traverse(site, 60.0, traverse_seed(a.seed, 0))
    tilt = np.degrees(np.arccos(np.cos(tr.rpy[:, 0]) * np.cos(tr.rpy[:, 1])))
    step = 40  # the 0.5 Hz frames of sim_heldout.py
    k_frames = np.arange(0, len(tr), step)
    k_max = int(k_frames[np.argmax(tilt[k_frames])])
    k_med = int(k_frames[np.argsort(tilt[k_frames])[len(k_frames) // 2]])
    for k in (k_max, k_med):
        p = tr.poses[k]
        print(f"sim seed {a.seed} frame {k}: tilt {tilt[k]:.1f} deg")
        views = renderer.render_rover(p, [rig["FrontLeft"], rig["FrontRight"]])
        (gl, sem), (gr, _) = views["FrontLeft"], views["FrontRight"]
        T = pose_to_matrix(*p)
        img = _overlay(det, gl, gr, T_ro, T, site.lander_xyz[:2])
        img = _outline(img, sem, site, (T @ T_ro)[:3, 3])
        panels.append(
            (
                f"lunarloc LAC look, seed {a.seed} frame {k}: tilt {tilt[k]:.0f} deg, sun {el:g} deg",
                img,
            )
        )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12.8, 7.8))
    for ax, (title, img) in zip(axes.ravel(), panels):
        ax.imshow(img, interpolation="antialiased")
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.suptitle(
        "Real LAC frames (top) and lunarloc's LAC-look site (bottom), detections drawn (small-rock stage "
        f"{'on' if cfg.small_rocks.enabled else 'off'}: green +)\nsimulated: true rocks within 6 m outlined, yellow "
        "r >= 0.1 m, cyan 0.025-0.1 m",
        fontsize=11,
    )
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=100)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
