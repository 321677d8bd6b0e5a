"""A closed-loop LAC stand-in over a lunarloc-simulated site: an agent file is loaded and
ticked through the stand-in leaderboard (:mod:`leaderboard.agents.agent_wrapper`,
:mod:`leaderboard.missionmanager.mission_manager`) while a kinematic rover integrates its
velocity commands over the simulated terrain and lunarloc's renderer draws what its
active cameras see.

This is the only file under ``tests/standins`` that imports lunarloc (the simulated world);
the ``carla`` and ``leaderboard`` stand-ins know nothing of it.

World model
-----------
* 20 Hz ticks (``dt`` = 0.05 s). The rover is kinematic: x, y, yaw integrate the clamped
  command (the base class clamps to 0.49 m/s, 4.13 rad/s, and hands the world a
  left-handed angular rate, which the vehicle flips back); z, roll and pitch rest it on the
  terrain (:func:`lunarloc.data.rover.terrain_pose`). Rocks do not stop it. ``slip`` (a
  fraction) makes it travel less than commanded; the odometry speeds report the command.
* Cameras: the mounts of the LAC rover (``docs/geometry.json`` of the NAV Lab repository),
  70 degree pinholes at the configured size, rendered at 10 Hz with the lamps at the light
  intensities the agent set (sun + lamps by default), handed over as CARLA does (BGRA).
* IMU: the leaderboard's (:mod:`leaderboard.agents.imu`), from the true pose.
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

STANDINS = Path(__file__).resolve().parent
if str(STANDINS) not in sys.path:
    sys.path.insert(0, str(STANDINS))

import carla  # noqa: E402  (the stand-in)
from leaderboard.agents.agent_wrapper import AgentWrapper  # noqa: E402
from leaderboard.agents.coordinate_conversion import carla_transform_from_rh  # noqa: E402
from leaderboard.missionmanager.mission_manager import MissionManager  # noqa: E402
from leaderboard.statistics.scores import mission_scores  # noqa: E402
from leaderboard.utils.constants import Constants  # noqa: E402

# ---- every lunarloc import of the harness
from lunarloc.sim.render import SEM_ROCK_OFFSET, RenderConfig, SiteRenderer, semantic_to_palette  # noqa: E402
from lunarloc.sim.rover import RoverConfig, terrain_pose  # noqa: E402
from lunarloc.sim.site import SiteConfig, generate_site  # noqa: E402
from lunarloc.core.geometry import pose_to_matrix  # noqa: E402
from lunarloc.perception.camera import T_CAM_OPTICAL, PinholeCamera  # noqa: E402

SP = carla.SensorPosition

# rover frame (x forward, y left, z up), metres / radians: (x, y, z, roll, pitch, yaw)
CAMERA_MOUNTS = {
    SP.FrontLeft: (0.28, 0.081, 0.131, 0.0, 0.0, 0.0),
    SP.FrontRight: (0.28, -0.081, 0.131, 0.0, 0.0, 0.0),
    SP.BackLeft: (-0.28, -0.081, 0.131, 0.0, 0.0, math.pi),
    SP.BackRight: (-0.28, 0.081, 0.131, 0.0, 0.0, math.pi),
    SP.Left: (0.015, 0.252, 0.132, 0.0, 0.0, math.pi / 2),
    SP.Right: (-0.015, -0.252, 0.132, 0.0, 0.0, -math.pi / 2),
    SP.Front: (0.636, -0.0147, 0.023, 0.0, math.pi / 2, 0.0),  # front arm at rest, looking down
    SP.Back: (-0.562, 0.017, 0.144, 0.0, -0.524, 0.0),  # back arm at rest
}
LIGHT_MOUNTS = {
    SP.FrontLeft: (0.28, 0.115, 0.131, 0.0, 0.0, 0.0),
    SP.FrontRight: (0.28, -0.115, 0.131, 0.0, 0.0, 0.0),
    SP.BackLeft: (-0.28, -0.115, 0.131, 0.0, 0.0, math.pi),
    SP.BackRight: (-0.28, 0.115, 0.131, 0.0, 0.0, math.pi),
    SP.Left: (-0.015, 0.252, 0.132, 0.0, 0.0, math.pi / 2),
    SP.Right: (0.015, -0.252, 0.132, 0.0, 0.0, -math.pi / 2),
    SP.Front: (0.636, 0.0147, 0.023, 0.0, math.pi / 2, 0.0),
    SP.Back: (-0.562, -0.013, 0.144, 0.0, -0.524, 0.0),
}
RENDERED_LAMPS = (
    "FrontLeft",
    "FrontRight",
    "BackLeft",
    "BackRight",
)  # the lamps lunarloc's renderer models


class _Actor:
    def __init__(self, T: np.ndarray):
        self.T = T

    def get_transform(self) -> carla.Transform:
        return carla_transform_from_rh(self.T)


class SimVehicle:
    """The rover as the leaderboard queries it (CARLA's left-handed transforms)."""

    def __init__(self, world: SimWorld):
        self.world = world
        self.camera_state = {p: False for p in SP}
        self.light_state = {p: 0.0 for p in SP}
        self.command = (0.0, 0.0)  # right-handed (m/s, rad/s) after the base class's clamp

    def get_transform(self) -> carla.Transform:
        return carla_transform_from_rh(self.world.T_world_rover)

    def get_odometry_speed(self) -> float:
        return self.command[0]

    def get_odometry_angular_speed(self) -> float:
        return self.command[1]

    def get_front_arm_angle(self) -> float:
        return 0.0

    get_back_arm_angle = get_front_drums_speed = get_back_drums_speed = get_radiator_cover_angle = (
        get_front_arm_angle
    )

    def get_current_power(self) -> float:
        return 283.0

    def get_consumed_power(self) -> float:
        return 0.0

    def get_camera_relative_transform(self, p) -> carla.Transform:
        return carla_transform_from_rh(pose_to_matrix(*CAMERA_MOUNTS[p]))

    def get_light_relative_transform(self, p) -> carla.Transform:
        return carla_transform_from_rh(pose_to_matrix(*LIGHT_MOUNTS[p]))

    def get_camera_state(self, p) -> bool:
        return self.camera_state[p]

    def get_light_state(self, p) -> float:
        return self.light_state[p]

    def set_camera_state(self, p, on) -> None:
        self.camera_state[p] = bool(on)

    def set_light_state(self, p, value) -> None:
        self.light_state[p] = float(value)

    def apply_velocity_control(self, control: carla.VehicleVelocityControl) -> None:
        self.command = (
            float(control.linear_target_velocity),
            -float(control.angular_target_velocity),
        )


class SimWorld:
    """A simulated site with one rover. ``start`` = (x, y, yaw) in the site frame (default
    the site's rover start, heading counter-clockwise about the lander)."""

    delta_seconds = 0.05

    def __init__(
        self,
        seed: int,
        n_rocks: int = 386,
        lighting: str = "sun+lamps",
        start=None,
        slip: float = 0.0,
        render: RenderConfig | None = None,
    ):
        self.site = generate_site(seed, SiteConfig(n_rocks=n_rocks))
        self.renderer = SiteRenderer(self.site, render or RenderConfig(lighting=lighting))
        self.rover_cfg = RoverConfig()
        if start is None:
            x, y = self.site.rover_start_xy
            lx, ly = self.site.lander_xyz[:2]
            start = (
                x,
                y,
                math.atan2(x - lx, -(y - ly)),
            )  # tangent, counter-clockwise about the lander
        self.x, self.y, self.yaw = (float(v) for v in start)
        self.slip = float(slip)
        self.vehicle = SimVehicle(self)
        self.lander = _Actor(pose_to_matrix(*self.site.lander_pose))
        self.platform_time_s = 0.0
        self._t0 = time.perf_counter()
        self.truth: list[np.ndarray] = []  # T_world_rover at every world tick
        self._update_pose()

    def _update_pose(self) -> None:
        xyz, rpy = terrain_pose(self.site, [self.x], [self.y], [self.yaw], self.rover_cfg)
        self.T_world_rover = pose_to_matrix(*xyz[0], *rpy[0])

    def tick(self) -> None:
        v, w = self.vehicle.command
        dt = self.delta_seconds
        v *= 1.0 - self.slip
        mid = self.yaw + 0.5 * w * dt
        self.x += v * dt * math.cos(mid)
        self.y += v * dt * math.sin(mid)
        self.yaw = (self.yaw + w * dt + math.pi) % (2 * math.pi) - math.pi
        self._update_pose()
        self.truth.append(self.T_world_rover.copy())
        self.platform_time_s = time.perf_counter() - self._t0

    def capture(self, cameras: dict, semantic=()) -> dict:
        """{pos: (BGRA (H, W, 4) uint8, semantic BGRA or None)} for {pos: (width, height)}."""
        lamps = {p.name: self.vehicle.light_state[p] for p in SP if p.name in RENDERED_LAMPS}
        out = {}
        by_size: dict[tuple[int, int], list] = {}
        for p, size in cameras.items():
            by_size.setdefault(tuple(size), []).append(p)
        for (w, h), ps in by_size.items():
            poses = [
                self.T_world_rover @ pose_to_matrix(*CAMERA_MOUNTS[p]) @ T_CAM_OPTICAL for p in ps
            ]
            shots = self.renderer.render(
                poses,
                PinholeCamera(w, h, 70.0),
                T_world_rover=self.T_world_rover,
                light_intensity=lamps,
            )
            for p, (gray, sem) in zip(ps, shots):
                bgra = np.empty((h, w, 4), np.uint8)
                bgra[:, :, :3] = gray[:, :, None]
                bgra[:, :, 3] = 255
                sem_bgra = None
                if p in semantic:
                    sem_bgra = np.empty((h, w, 4), np.uint8)
                    sem_bgra[:, :, :3] = semantic_to_palette(sem)
                    sem_bgra[:, :, 3] = 255
                out[p] = (bgra, sem_bgra)
        return out

    def write_reference(self, path) -> Path:
        """The site's true rocks as lunarloc's ``id,x,y,z,radius`` CSV (a reference map)."""
        return self.site.write_rocks_csv(path)

    def ground_truth_map(self, constants: Constants) -> np.ndarray:
        """The leaderboard's true map: per cell 16 vertical rays (a 4 x 4 grid 3.75 cm apart
        for 15 cm cells) from 25 m; the mean hit height, and rock if any ray hits a rock."""
        from leaderboard.agents.geometric_map import cell_centres

        c = cell_centres(constants)
        off = (np.arange(4) * 2 - 3) * constants.cell_size / 8
        X, Y = np.meshgrid(c, c, indexing="ij")
        ox, oy = np.meshgrid(off, off, indexing="ij")
        px = (X[:, :, None] + ox.ravel()).ravel()
        py = (Y[:, :, None] + oy.ravel()).ravel()
        origins = np.column_stack([px, py, np.full(px.size, 25.0)])
        dirs = np.tile([0.0, 0.0, -1.0], (px.size, 1))
        t, label = self.renderer.cast_rays(origins, dirs)
        n = constants.cell_number
        z = (25.0 - t).reshape(n, n, 16)
        rock = (label >= SEM_ROCK_OFFSET).reshape(n, n, 16)
        miss = ~np.isfinite(z).all(axis=2)
        m = np.empty((n, n, 4))
        m[:, :, 0], m[:, :, 1] = X, Y
        m[:, :, 2] = np.where(miss, 0.0, np.where(np.isfinite(z), z, 0).mean(axis=2))
        m[:, :, 3] = np.where(miss, False, rock.any(axis=2))
        return m


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(v)


def write_agent_config(
    folder, world: SimWorld, *, width: int, height: int, output: str = "agent-output", **settings
) -> Path:
    """An agent's configuration for `world` in `folder` (created): the site's true rocks
    written as the reference map (``rocks.csv``) and ``lunarloc.toml`` naming it, with the
    image size, the agent's output folder (relative to `folder`; "" for none) and any further
    ``settings`` of the agent's config (``lac_map=True``, ...). Returns the config's path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    world.write_reference(folder / "rocks.csv")
    conf = folder / "lunarloc.toml"
    items = {"reference": "rocks.csv", "width": width, "height": height, "output": output}
    conf.write_text("".join(f"{k} = {_toml_value(v)}\n" for k, v in {**items, **settings}.items()))
    return conf


def prepare_site(
    folder, seed: int, *, rocks: int = 386, lighting: str = "sun+lamps", **config
) -> tuple[SimWorld, Path]:
    """The world of site `seed` (`rocks` rocks, `lighting`) and an agent's configuration for it
    in `folder` (:func:`write_agent_config`, which takes `config`): what a closed-loop
    benchmark sets up per site. Returns the world and the config's path."""
    world = SimWorld(seed, n_rocks=rocks, lighting=lighting)
    return world, write_agent_config(folder, world, **config)


@dataclass
class Run:
    """What a closed-loop run produced (times in seconds)."""

    agent: object
    ticks: int
    mission_time_s: float
    truth: list = field(default_factory=list)  # T_world_rover at each agent tick
    run_step_s: list = field(default_factory=list)
    run_step_cpu_s: list = field(default_factory=list)  # process CPU time, robust to other load
    get_transform_calls: int = 0
    setup_s: float = 0.0
    scores: dict | None = None


def run_agent(
    agent_file,
    conf_path,
    world: SimWorld,
    duration_s: float,
    *,
    evaluation: bool = True,
    constants: Constants | None = None,
    score: bool = False,
    quiet: bool = True,
    observe=None,
) -> Run:
    """Load `agent_file` through the stand-in wrapper, set it up with `conf_path`, and run
    the mission for `duration_s` of mission time (or until the agent calls
    ``mission_complete()``). ``run_step`` times and ``get_transform()`` calls are recorded;
    ``observe(agent)``, when given, is called after every ``run_step``."""
    constants = constants or Constants()
    t0 = time.perf_counter()
    wrapper = AgentWrapper(
        world, str(agent_file), "" if conf_path is None else str(conf_path), evaluation
    )
    agent = wrapper.agent
    run = Run(agent=agent, ticks=0, mission_time_s=0.0)
    inner_run_step, inner_get_transform = agent.run_step, agent.get_transform

    def timed_run_step(input_data):
        s, c = time.perf_counter(), time.process_time()
        try:
            return inner_run_step(input_data)
        finally:
            run.run_step_s.append(time.perf_counter() - s)
            run.run_step_cpu_s.append(time.process_time() - c)
            run.truth.append(world.T_world_rover.copy())
            if observe is not None:
                observe(agent)

    def counted_get_transform():
        run.get_transform_calls += 1
        return inner_get_transform()

    agent.run_step, agent.get_transform = timed_run_step, counted_get_transform
    manager = MissionManager(world, world.vehicle, wrapper, duration_s)
    stdout = sys.stdout
    try:
        if quiet:
            sys.stdout = open(
                os.devnull, "w"
            )  # the base class prints a line per tick, as the real one does
        wrapper.setup(world.vehicle, world.lander, constants)
        run.setup_s = time.perf_counter() - t0
        manager.run()
    finally:
        if quiet:
            sys.stdout.close()
            sys.stdout = stdout
    run.ticks, run.mission_time_s = manager.ticks, manager.mission_duration_s
    if score:
        run.scores = mission_scores(
            world.ground_truth_map(constants),
            wrapper.get_agent_map(),
            run.mission_time_s,
            wrapper.agent_fiducials,
            constants,
        )
    return run
