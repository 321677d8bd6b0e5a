"""Figure: the real LAC frame beside lunarloc's renders at a similar pose.

    python benchmarks/lac_vs_sim.py [--real ../shared/data/lac-real] [--seed 0] \
        [--out docs/images/lac_vs_sim.png]

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

from lunarloc.data.render import Lighting, RenderConfig, SiteRenderer, semantic_to_palette
from lunarloc.data.rover import RoverConfig, terrain_pose
from lunarloc.data.site import generate_site
from lunarloc.perception.camera import PinholeCamera, ipex_rig

# The real frame's shadows (the rover's own falls ahead and about 18 degrees left of
# its heading, reaching some metres ahead) put the sun near azimuth 276 degrees and a
# few degrees high; read off the image by eye, not fitted.
SUN_AZIMUTH_DEG = 276.0
SUN_ELEVATION_DEG = 6.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", type=Path, default=Path("../shared/data/lac-real"))
    ap.add_argument("--seed", type=int, default=0, help="our site's seed")
    ap.add_argument("--out", type=Path, default=Path("docs/images/lac_vs_sim.png"))
    ap.add_argument("--semantic-out", type=Path, default=None, help="also save our semantic image (LAC palette)")
    args = ap.parse_args()

    real_png, pose_json = args.real / "FrontLeft_99.png", args.real / "pose_99.json"
    if not real_png.exists() or not pose_json.exists():
        print(f"real LAC frame not found under {args.real}; nothing to compare", file=sys.stderr)
        return 2
    from PIL import Image

    real = np.asarray(Image.open(real_png).convert("L"))
    pose = json.loads(pose_json.read_text())

    site = generate_site(args.seed)
    xyz, rpy = terrain_pose(site, np.array([pose["x"]]), np.array([pose["y"]]), np.array([pose["yaw"]]), RoverConfig())
    rover = np.concatenate([xyz[0], rpy[0]])
    mount = ipex_rig(PinholeCamera(real.shape[1], real.shape[0]))["FrontLeft"]
    base = RenderConfig(sun_elevation_deg=SUN_ELEVATION_DEG, sun_azimuth_deg=SUN_AZIMUTH_DEG)
    renderer = SiteRenderer(site, base)
    panels = [("real LAC frame (FrontLeft 99)", real)]
    for title, cfg in (
        (f"lunarloc, sun+lamps (sun {SUN_ELEVATION_DEG:g} deg)", base),
        ("lunarloc, sun only", replace(base, lighting=Lighting.SUN)),
        ("lunarloc, lamps only at night (sun -5 deg)", replace(base, lighting=Lighting.LAMPS, sun_elevation_deg=-5.0)),
    ):
        gray, sem = renderer.with_config(cfg).render_rover(rover, [mount])["FrontLeft"]
        panels.append((title, gray))
        if cfg is base and args.semantic_out is not None:
            args.semantic_out.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(semantic_to_palette(sem)).save(args.semantic_out, optimize=True)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12.8, 7.6))
    for ax, (title, img) in zip(axes.ravel(), panels):
        ax.imshow(img, cmap="gray", vmin=0, vmax=255, interpolation="antialiased")
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.suptitle(
        f"Real LAC frame vs lunarloc at the same rover x, y, yaw (site seed {args.seed}; our rocks and terrain)",
        fontsize=11,
    )
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
