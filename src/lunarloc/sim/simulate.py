"""Simulated traverses: site + rover + renderer -> `.lac` archives with ground truth.

One call for the common case (:func:`simulate_dataset`), the steps for experts
(:func:`simulate_site`, :func:`simulate_traverse`, :func:`write_example_images`).

What an archive holds (see :mod:`lunarloc.io.lac.archive` for the layout)
--------------------------------------------------------------------
* ``frames.csv``: ground-truth rover pose (site frame), IMU (rover frame), mission
  time, speeds, at the rover rate (20 Hz); frames numbered from 0.
* Camera tables and images for the IPEx rig (FrontLeft/FrontRight/BackLeft/
  BackRight) every ``rate_hz / image_rate_hz`` frames; camera poses are relative
  to the rover. Grayscale ``uint8``; semantic ``uint16`` ids (0 sky, 1 ground,
  2 lander, 3 fiducial, 10 + rock id) or, with ``semantic_format="palette"``,
  ``(H, W, 3) uint8`` in the LAC palette (see :mod:`lunarloc.sim.render`).
  ``light_intensity`` (initial.toml and camera tables) is the lamps' intensity
  when the lighting has lamps, else 0.
* ``custom/rocks.csv`` (``id,x,y,z,radius``: ground-truth rocks, site frame) and
  ``custom/odometry.csv`` (``frame,x,y,z,roll,pitch,yaw``: the drifting odometry
  estimate, site frame).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lunarloc.sim.render import (
    RenderConfig,
    SemanticFormat,
    SiteRenderer,
    colorize_semantic,
    semantic_to_palette,
)
from lunarloc.sim.rover import (
    ImuConfig,
    OdometryConfig,
    RoverConfig,
    Trajectory,
    plan_traverse,
    simulate_imu,
    simulate_odometry,
)
from lunarloc.sim.site import Site, SiteConfig, generate_site
from lunarloc.core.errors import ConfigError
from lunarloc.core.geometry import matrix_to_pose
from lunarloc.perception.camera import PinholeCamera, ipex_rig

__all__ = [
    "SimulationConfig",
    "simulate_site",
    "traverse_seed",
    "simulate_traverse",
    "simulate_dataset",
    "write_example_images",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

ALL_CAMERAS = ("FrontLeft", "FrontRight", "BackLeft", "BackRight")


@dataclass(frozen=True)
class SimulationConfig:
    """Everything a simulated dataset depends on (besides the seed)."""

    site: SiteConfig = field(default_factory=SiteConfig)
    rover: RoverConfig = field(default_factory=RoverConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    duration_s: float = 120.0  # length of each traverse
    image_rate_hz: float = 2.0  # camera rate (LAC: up to 10 Hz); must divide the rover rate
    width: int = 1280  # image size in pixels
    height: int = 720
    cameras: tuple[str, ...] = ALL_CAMERAS  # cameras that record
    semantic: bool = True  # also store semantic images
    # per-rock ids (uint16) or the LAC palette (RGB)
    semantic_format: SemanticFormat = SemanticFormat.IDS
    initial_power_wh: float = 283.0  # battery charge at the start
    power_draw_w: float = 30.0  # constant draw (power column falls linearly)

    def __post_init__(self) -> None:
        object.__setattr__(self, "semantic_format", SemanticFormat.parse(self.semantic_format))

    @property
    def light_intensity(self) -> float:
        """The LAC ``light_intensity`` the archive records (0 when the lighting has no lamps)."""
        return float(self.render.lamp_intensity) if self.render.lighting.has_lamps else 0.0

    def validate(self) -> None:
        self.render.validate()
        if self.duration_s <= 0:
            raise ConfigError(f"duration_s={self.duration_s} must be > 0")
        if not 0 < self.image_rate_hz <= 10.0:
            raise ConfigError(f"image_rate_hz={self.image_rate_hz} must be in (0, 10]")
        step = self.rover.rate_hz / self.image_rate_hz
        if abs(step - round(step)) > 1e-6:
            raise ConfigError(
                f"image_rate_hz={self.image_rate_hz} must divide the rover rate "
                f"{self.rover.rate_hz} Hz"
            )
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"image size {self.width}x{self.height} is too small")
        unknown = [c for c in self.cameras if c not in ALL_CAMERAS]
        if unknown:
            raise ConfigError(f"unknown camera(s) {unknown}; known: {', '.join(ALL_CAMERAS)}")

    @property
    def frames_per_image(self) -> int:
        return int(round(self.rover.rate_hz / self.image_rate_hz))

    def to_dict(self) -> dict:
        return asdict(self)


def simulate_site(seed: int = 0, config: SiteConfig | SimulationConfig | None = None) -> Site:
    """The procedural site for `seed` (see :func:`lunarloc.sim.site.generate_site`)."""
    if isinstance(config, SimulationConfig):
        config = config.site
    return generate_site(seed, config)


def traverse_seed(site_seed: int, index: int) -> int:
    """Seed of traverse `index` of the site with `site_seed` (waypoints, noise)."""
    return int(np.random.SeedSequence([int(site_seed), int(index), 0x7EA]).generate_state(1)[0])


def _camera_config(cfg: SimulationConfig) -> dict:
    return {
        name: {
            "camera_active": name in cfg.cameras,
            "light_intensity": cfg.light_intensity,
            "width": int(cfg.width),
            "height": int(cfg.height),
            "use_semantic": bool(cfg.semantic and name in cfg.cameras),
        }
        for name in ALL_CAMERAS
    }


def simulate_traverse(
    site: Site,
    path: str | Path,
    index: int = 0,
    config: SimulationConfig | None = None,
    *,
    renderer: SiteRenderer | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[Path, Trajectory]:
    """Simulate traverse `index` of `site` and write it as a `.lac` archive at `path`.

    Every traverse starts at the site's rover start (like the LAC dataset) and
    drives to its own random waypoints. `progress(n)` is called after each frame
    with images with the number of rover frames done so far. Returns the archive
    path and the ground-truth trajectory.
    """
    from lunarloc.io.lac.archive import LacWriter, lander_pose_relative

    cfg = config or SimulationConfig()
    cfg.validate()
    renderer = renderer or SiteRenderer(site, cfg.render)
    seed = traverse_seed(site.seed, index)
    traj = plan_traverse(site, cfg.duration_s, seed=seed, config=cfg.rover)
    accel, gyro = simulate_imu(traj, seed=seed, config=cfg.imu)
    odom = simulate_odometry(traj, seed=seed, config=cfg.odometry)
    rig = ipex_rig(PinholeCamera(cfg.width, cfg.height))
    mounts = [rig[name] for name in cfg.cameras]
    cam_poses = {m.name: [float(v) for v in matrix_to_pose(m.T_rover_cam)] for m in mounts}
    initial = {
        "fiducials": False,
        # rover-relative, as the LAC stores it
        "lander": lander_pose_relative(traj.poses[0], site.lander_pose),
        "rover": [float(v) for v in traj.poses[0]],
        "cameras": _camera_config(cfg),
    }
    desc = (
        f"lunarloc simulated traverse {index} of site seed {site.seed}: {cfg.duration_s:g} s, "
        f"images {cfg.width}x{cfg.height} at {cfg.image_rate_hz:g} Hz, sun elevation "
        f"{cfg.render.sun_elevation_deg:g} deg azimuth {cfg.render.sun_azimuth_deg:g} deg, "
        f"lighting {cfg.render.lighting}"
    )
    step = cfg.frames_per_image
    power = cfg.initial_power_wh - cfg.power_draw_w * traj.t / 3600.0
    path = Path(path)
    with LacWriter(path, initial, description=desc) as w:
        for k in range(len(traj)):
            x, y, z, roll, pitch, yaw = (float(v) for v in traj.poses[k])
            w.add_frame(
                k,
                x=x,
                y=y,
                z=z,
                roll=roll,
                pitch=pitch,
                yaw=yaw,
                accel_x=accel[k, 0],
                accel_y=accel[k, 1],
                accel_z=accel[k, 2],
                gyro_x=gyro[k, 0],
                gyro_y=gyro[k, 1],
                gyro_z=gyro[k, 2],
                mission_time=float(traj.t[k]),
                power=float(power[k]),
                linear_speed=float(traj.linear_speed[k]),
                angular_speed=float(traj.angular_speed[k]),
                cover_angle=0.0,
            )
            if k % step == 0 and mounts:
                images = renderer.render_rover(traj.poses[k], mounts)
                for m in mounts:
                    gray, sem = images[m.name]
                    if cfg.semantic and cfg.semantic_format is SemanticFormat.PALETTE:
                        sem = semantic_to_palette(sem)
                    w.add_camera_frame(
                        m.name,
                        k,
                        cam_poses[m.name],
                        light_intensity=cfg.light_intensity,
                        grayscale=gray,
                        semantic=sem if cfg.semantic else None,
                    )
                if progress is not None:
                    progress(k + 1)
        w.add_custom("rocks", ["id", "x", "y", "z", "radius"], _rock_rows(site))
        w.add_custom(
            "odometry",
            ["frame", "x", "y", "z", "roll", "pitch", "yaw"],
            [[k] + [float(v) for v in odom[k]] for k in range(len(traj))],
        )
    if progress is not None:
        progress(len(traj))
    logger.info("wrote %s (%d frames, %.1f m)", path, len(traj), traj.path_length())
    return path, traj


def _rock_rows(site: Site) -> list[list]:
    return [[int(r[0])] + [float(v) for v in r[1:]] for r in site.rocks_table()]


def simulate_dataset(
    seed: int,
    n_traverses: int,
    out_dir: str | Path,
    config: SimulationConfig | None = None,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> list[Path]:
    """Write ``rocks.csv``, ``simulation.json`` and ``traverse_<i>.lac`` (i = 0..N-1) to `out_dir`.

    `progress(traverse_index, frames_done)` is called as frames are rendered.
    """
    import json

    cfg = config or SimulationConfig()
    cfg.validate()
    if n_traverses < 0:
        raise ConfigError(f"n_traverses={n_traverses} must be >= 0")
    out = Path(out_dir)
    site = simulate_site(seed, cfg.site)
    # the renderer first: without the `sim` extra this raises DependencyError before any file
    # is written (rocks.csv and simulation.json alone would make a rerun refuse to overwrite)
    renderer = SiteRenderer(site, cfg.render) if n_traverses else None
    out.mkdir(parents=True, exist_ok=True)
    site.write_rocks_csv(out / "rocks.csv")
    # the LAC ground-truth map (x, y, height, rock)
    from lunarloc.io.overhead import (
        write_site_geometric_map,
    )

    write_site_geometric_map(site, out / "geometric_map.npy")
    from lunarloc.io.outputs import write_text

    write_text(out / "simulation.json", json.dumps({"seed": int(seed), **cfg.to_dict()}, indent=2))
    paths = []
    for i in range(n_traverses):
        cb = (lambda n, i=i: progress(i, n)) if progress is not None else None
        p, _ = simulate_traverse(
            site, out / f"traverse_{i}.lac", i, cfg, renderer=renderer, progress=cb
        )
        paths.append(p)
    return paths


def write_example_images(
    out_dir: str | Path,
    seed: int = 0,
    *,
    config: SimulationConfig | None = None,
    time_s: float | None = None,
) -> list[Path]:
    """Render the FrontLeft camera of traverse 0 and save ``frontleft_grayscale.png``
    and ``frontleft_semantic.png`` (colourised) to `out_dir`.

    The frame is at `time_s` seconds, or (None) the frame of the first 60 s that
    sees the most rocks (chosen on low-resolution previews).
    """
    from PIL import Image

    cfg = config or SimulationConfig()
    cfg.validate()
    site = simulate_site(seed, cfg.site)
    traj = plan_traverse(
        site,
        61.0 if time_s is None else max(time_s, 1.0) + 1.0,
        seed=traverse_seed(seed, 0),
        config=cfg.rover,
    )
    renderer = SiteRenderer(site, cfg.render)
    if time_s is None:
        preview = ipex_rig(PinholeCamera(160, 90))["FrontLeft"]
        counts = []
        for k in range(0, len(traj), 40):
            _, sem = renderer.render_rover(traj.poses[k], [preview])["FrontLeft"]
            counts.append((len(np.unique(sem[sem >= 10])), k))
        k = max(counts)[1]
    else:
        k = min(int(round(time_s * cfg.rover.rate_hz)), len(traj) - 1)
    mount = ipex_rig(PinholeCamera(cfg.width, cfg.height))["FrontLeft"]
    gray, sem = renderer.render_rover(traj.poses[k], [mount])["FrontLeft"]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p_gray = out / "frontleft_grayscale.png"
    p_sem = out / "frontleft_semantic.png"
    Image.fromarray(gray).save(p_gray, optimize=True)
    Image.fromarray(colorize_semantic(sem)).save(p_sem, optimize=True)
    return [p_gray, p_sem]
