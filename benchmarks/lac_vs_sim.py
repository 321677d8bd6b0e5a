"""Figure: the real LAC frame beside lunarloc's renders at a similar pose.

    python benchmarks/lac_vs_sim.py [--real ../shared/data/lac-real] [--seed 0] \
        [--out docs/images/lac_vs_sim.png]
    python benchmarks/lac_vs_sim.py --detections --out docs/images/lac_vs_sim_detections.png

With ``--detections`` each panel shows what the detector (default settings, the stereo pair,
the lander's position known) makes of it: kept masks green with a cross, range and radius,
rejected masks coloured by the filter that rejected them (legend in the corner); in our
renders the true rocks of radius >= 0.1 m within 6 m of the camera are outlined in yellow,
so a miss shows as a yellow outline without a cross.

Panels: the real FrontLeft frame 99; ours with ``sun+lamps`` at the real frame's
rover x, y and yaw (z, roll and pitch from our terrain, which differs from the LAC
map), the sun low behind-right of the rover as the real frame's shadows suggest;
ours with the sun only (the renderer's look before the lamps); ours at night
(sun below the horizon, lamps only). Rocks are our site's, not the LAC's: the
figure compares the look, not the scene.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from lunarloc.sim.render import Lighting, RenderConfig, SiteRenderer, semantic_to_palette
from lunarloc.sim.rover import RoverConfig, terrain_pose
from lunarloc.sim.site import generate_site
from lunarloc.core.geometry import pose_to_matrix
from lunarloc.perception.camera import PinholeCamera, ipex_rig

# The real frame's shadows (the rover's own falls ahead and about 18 degrees left of
# its heading, reaching some metres ahead) put the sun near azimuth 276 degrees and a
# few degrees high; read off the image by eye, not fitted.
SUN_AZIMUTH_DEG = 276.0
SUN_ELEVATION_DEG = 6.0


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--real", type=Path, default=Path("../shared/data/lac-real"))
    ap.add_argument("--seed", type=int, default=0, help="our site's seed")
    ap.add_argument("--out", type=Path, default=Path("docs/images/lac_vs_sim.png"))
    ap.add_argument(
        "--semantic-out", type=Path, default=None, help="also save our semantic image (LAC palette)"
    )
    ap.add_argument(
        "--detections",
        action="store_true",
        help="draw the detector's masks and detections on each panel",
    )
    args = ap.parse_args()

    real_png, pose_json = args.real / "FrontLeft_99.png", args.real / "pose_99.json"
    if not real_png.exists() or not pose_json.exists():
        print(f"real LAC frame not found under {args.real}; nothing to compare", file=sys.stderr)
        return 2
    from PIL import Image

    real = np.asarray(Image.open(real_png).convert("L"))
    pose = json.loads(pose_json.read_text())
    real_right = args.real / "FrontRight_99.png"
    if args.detections and not real_right.exists():
        print(
            f"no FrontRight_99.png under {args.real}: --detections needs the stereo pair",
            file=sys.stderr,
        )
        return 2

    site = generate_site(args.seed)
    xyz, rpy = terrain_pose(
        site, np.array([pose["x"]]), np.array([pose["y"]]), np.array([pose["yaw"]]), RoverConfig()
    )
    rover = np.concatenate([xyz[0], rpy[0]])
    camera = PinholeCamera(real.shape[1], real.shape[0])
    rig = ipex_rig(camera)
    mount = rig["FrontLeft"]
    base = RenderConfig(sun_elevation_deg=SUN_ELEVATION_DEG, sun_azimuth_deg=SUN_AZIMUTH_DEG)
    renderer = SiteRenderer(site, base)
    real_pose = pose_to_matrix(*[float(pose[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")])
    panels = [("real LAC frame (FrontLeft 99)", real)]
    if args.detections:  # the LAC lander stands at the site centre, the map origin
        right = np.asarray(Image.open(real_right).convert("L"))
        panels = [(panels[0][0], _detected(real, right, real_pose, np.zeros(2), camera, rig))]
    for title, cfg in (
        (f"lunarloc, sun+lamps (sun {SUN_ELEVATION_DEG:g} deg)", base),
        ("lunarloc, sun only", replace(base, lighting=Lighting.SUN)),
        (
            "lunarloc, lamps only at night (sun -5 deg)",
            replace(base, lighting=Lighting.LAMPS, sun_elevation_deg=-5.0),
        ),
    ):
        mounts = [mount, rig["FrontRight"]] if args.detections else [mount]
        views = renderer.with_config(cfg).render_rover(rover, mounts)
        gray, sem = views["FrontLeft"]
        if args.detections:
            img = _detected(
                gray,
                views["FrontRight"][0],
                pose_to_matrix(*rover),
                site.lander_xyz[:2],
                camera,
                rig,
            )
            panels.append(
                (
                    title,
                    _outline_rocks(img, sem, site, pose_to_matrix(*rover) @ mount.T_rover_optical),
                )
            )
        else:
            panels.append((title, gray))
        if cfg is base and args.semantic_out is not None:
            args.semantic_out.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(semantic_to_palette(sem)).save(args.semantic_out, optimize=True)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12.8, 7.6))
    for ax, (title, img) in zip(axes.ravel(), panels):
        ax.imshow(
            img, cmap="gray", vmin=0, vmax=255, interpolation="antialiased"
        )  # RGB when detected
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    what = (
        "detections (green, +), rejected masks by filter; yellow: our true rocks r >= 0.1 m within 6 m"
        if args.detections
        else ""
    )
    fig.suptitle(
        f"Real LAC frame vs lunarloc at the same rover x, y, yaw (site seed {args.seed}; our rocks and terrain)"
        + (f"\n{what}" if what else ""),
        fontsize=11,
    )
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")
    return 0


def _detected(left, right, T_map_rover, lander_xy, camera, rig) -> np.ndarray:
    """The detector's overlay (RGB) of one FrontLeft/FrontRight pair; prints its detections."""
    from lunarloc.perception.detector import Detector, DetectorConfig, debug_overlay

    det = Detector(DetectorConfig(), camera)
    pr = det.detect_pair(
        left,
        right,
        rig["FrontLeft"].T_rover_optical,
        T_map_rover,
        "FrontLeft",
        lander_xy=np.asarray(lander_xy, float),
    )
    print(
        f"  {len(pr.detections)} detections: "
        + ", ".join(f"{d.depth_m:.1f} m r {d.radius_m:.2f}" for d in pr.detections)
    )
    return debug_overlay(left, pr)[:, : left.shape[1], ::-1].copy()


def _outline_rocks(img: np.ndarray, sem: np.ndarray, site, T_map_optical: np.ndarray) -> np.ndarray:
    """Outline in yellow the site's rocks of radius >= 0.1 m whose centre lies within 6 m of
    the camera, from the semantic ids (`sem`, the renderer's rock ids)."""
    import cv2

    from lunarloc.sim.render import semantic_to_rock_id

    ids, cam = semantic_to_rock_id(sem), T_map_optical[:3, 3]
    for k in range(len(site.rocks)):
        if site.rocks.radii[k] < 0.1 or np.linalg.norm(site.rocks.centers[k] - cam) > 6.0:
            continue
        m = (ids == int(site.rocks.ids[k])).astype(np.uint8)
        if m.any():
            contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(img, contours, -1, (255, 255, 0), 1)
    return img


if __name__ == "__main__":
    sys.exit(main())
