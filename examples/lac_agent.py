"""A Lunar Autonomy Challenge leaderboard agent that localizes against a reference rock map
with lunarloc. Give the leaderboard this file as the agent and a TOML file as its config::

    python leaderboard/leaderboard_evaluator.py --agent=examples/lac_agent.py \\
        --agent-config=lunarloc.toml ...

The leaderboard imports the file, calls ``get_entry_point()`` and builds the class with no
arguments; then ``use_fiducials()``, ``setup(path_to_conf_file)``, ``sensors()``, and every
20 Hz tick ``run_step(input_data)`` (images every other tick), ``finalize()`` at the end.

Settings (``lunarloc.toml``; every key optional, relative paths from the TOML's folder)::

    reference = "rocks.csv"   # the reference map (any format lunarloc.load_reference reads),
                              # in the leaderboard's world frame; "" or absent: no reference
    width = 1280              # front stereo pair resolution (the LAC allows up to 2448 x 2048)
    height = 720
    odometry = "visual"       # "visual" (stereo VO, IMU between pairs) or "imu"
    output = "lunarloc-out"   # finalize() writes trajectory.csv and summary.json here; "" none
    light_intensity = 1.0     # the front lamps (0-1)
    loop_radius_m = 0.0       # radius of the loop driven about the lander; 0: the start's distance
    speed_mps = 0.3           # driving speed (the leaderboard clamps to 0.49)
    warm_up = true            # compile and warm caches in setup(), before the mission clock runs
    lac_map = true            # fill the leaderboard's geometric map (lunarloc.LacMapper): cells as they
                              # become confident during the run, the whole map in finalize(); false:
                              # a team's own mapper fills it (MAPPER HOOK)
    lac_map_cells_per_tick = 400  # at most this many cells written a tick (bounds the tick's cost)
    lac_map_small_rocks = true    # with lac_map: the detector's small-rock stage (rocks under 5 cm;
                                  # on by default in the detector: false turns it off)

Without the leaderboard installed the class derives from lunarloc's mirror of its base
class (:class:`lunarloc.LacAgentBase`), so :class:`lunarloc.PlaybackAgent` can replay a
recording through it in the leaderboard's call order (``tests/test_online_component.py``).

Driving is not lunarloc's job: ``run_step`` steers a loop about the lander from the
estimated pose so that the rover moves and sees rocks; a team plans here instead. The
geometric map the LAC scores: lunarloc's mapper fills it (``lac_map``, on), during the run
(``lunarloc.mapping.lac_map.LacMapWriter.step`` every tick: the cells that became confident,
at most ``lac_map_cells_per_tick`` a tick) and whole in ``finalize()``; with ``lac_map = false``
a team's own mapper goes into the ``MAPPER HOOK``.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np

import lunarloc
from lunarloc import (
    CameraRig,
    LacMapper,
    OnlineConfig,
    OnlineLocalizer,
    as_transform_matrix,
    load_reference,
)
from lunarloc.core.geometry import matrix_to_pose
from lunarloc.mapping.lac_map import LacMapWriter

try:  # the leaderboard's own types when it is installed
    import carla
    from leaderboard.autoagents.autonomous_agent import AutonomousAgent

    SensorPosition, VehicleVelocityControl = carla.SensorPosition, carla.VehicleVelocityControl
except ImportError:  # lunarloc's mirror of them (same names, same behaviour)
    from lunarloc import LacAgentBase as AutonomousAgent
    from lunarloc import SensorPosition, VehicleVelocityControl

try:
    import tomllib
except ImportError:  # Python 3.10 (the leaderboard's): lunarloc depends on tomli there
    import tomli as tomllib

log = logging.getLogger(__name__)

STEREO = ("FrontLeft", "FrontRight")
DEFAULTS = {
    "reference": "",
    "width": 1280,
    "height": 720,
    "odometry": "visual",
    "output": "lunarloc-out",
    "light_intensity": 1.0,
    "loop_radius_m": 0.0,
    "speed_mps": 0.3,
    "warm_up": True,
    "lac_map": True,
    "lac_map_cells_per_tick": 400,
    "lac_map_small_rocks": True,
}


def get_entry_point() -> str:
    return "LunarLocAgent"


class LunarLocAgent(AutonomousAgent):
    """Localizes every tick (``self.estimate``) and drives a loop about the lander."""

    # -- configuration ----------------------------------------------------------------------
    def setup(self, path_to_conf_file) -> None:
        self.settings = settings = _read_settings(path_to_conf_file)
        base = Path(path_to_conf_file).resolve().parent if path_to_conf_file else Path.cwd()
        ref = settings["reference"]
        self.reference = load_reference(base / ref) if ref else None
        self.estimate = None
        self.localizer = None
        self._ticks = 0
        self._rows = None
        out = settings["output"]
        self.output_dir = (base / out) if out else None
        if self.output_dir is not None:
            self.output_dir.mkdir(parents=True, exist_ok=True)
            self._rows = open(
                self.output_dir / "trajectory.csv", "w", buffering=1 << 16
            )  # bounded memory
            self._rows.write(
                "mission_time_s,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad,localized,fixes\n"
            )
        # the initial poses are known before the first tick; the camera poses are not (no vehicle
        # status yet), so the rig starts as the LAC's known mounts, checked at the first tick
        self.localizer = self._make_localizer(rig=None)
        if settings["warm_up"]:
            log.info("lunarloc warm-up took %.1f s", self.localizer.warm_up())
        # where the loop goes: the lander's world position (the initial pose composed with the
        # lander's pose relative to the rover), at the rover's starting distance from it
        T0 = as_transform_matrix(self.get_initial_position(), "get_initial_position()")
        T_rl = as_transform_matrix(
            self.get_initial_lander_position(), "get_initial_lander_position()"
        )
        self.lander_xy = (T0 @ T_rl)[:2, 3]
        r0 = float(np.linalg.norm(T0[:2, 3] - self.lander_xy))
        self.loop_radius_m = settings["loop_radius_m"] or min(max(r0, 3.5), 10.0)
        self.map_writer = (
            None  # lac_map: lunarloc's mapper's writer into get_geometric_map() (first tick)
        )
        self.map_write_cpu_s = []  # lac_map: CPU seconds of each tick's map writing
        self.map_finish_cpu_s = None  # lac_map: CPU seconds of writing the whole map in finalize()
        self.mapper = None  # MAPPER HOOK: a mapper of the team's own, fed every tick (see run_step)

    def use_fiducials(self) -> bool:
        return False  # the localization points (150 of 1000) count only without fiducials

    def sensors(self) -> dict:
        s = self.settings
        return {
            p: {
                "camera_active": p.name in STEREO,
                "light_intensity": s["light_intensity"] if p.name in STEREO else 0.0,
                "width": s["width"],
                "height": s["height"],
                "use_semantic": False,
            }
            for p in SensorPosition
        }

    def _make_localizer(self, rig) -> OnlineLocalizer:
        s = self.settings
        rig = rig or CameraRig.from_sensors(self.sensors())  # the LAC mounts at the configured size
        lac_mapper = LacMapper() if s["lac_map"] else None  # fed by the localizer at its keyframes
        detector_config = None
        # the any-ray rule flags rocks under 5 cm: the small-rock stage (on by default) finds them;
        # with lac_map, lac_map_small_rocks = false turns it off
        if s["lac_map"] and not s["lac_map_small_rocks"]:
            from dataclasses import replace

            from lunarloc.perception.detector import DetectorConfig, scaled_detector_config

            base = DetectorConfig()
            base = replace(base, small_rocks=replace(base.small_rocks, enabled=False))
            detector_config = scaled_detector_config(rig.camera.width, base)
        self.map_writer = None  # a new mapper: a new writer at the next tick
        return OnlineLocalizer(
            self.reference,
            self.get_initial_position(),
            rig=rig,
            config=OnlineConfig(visual_odometry=s["odometry"] == "visual"),
            detector_config=detector_config,
            lander_pose=self.get_initial_lander_position(),
            mapper=lac_mapper,
        )

    # -- every tick ---------------------------------------------------------------------------
    def run_step(self, input_data):
        if self._ticks == 0:  # the first tick has a vehicle status: check the camera mounts
            poses = {p: self.get_camera_position(p) for p in SensorPosition if p.name in STEREO}
            rig = CameraRig.from_sensors(self.sensors(), poses)
            if not self.localizer.rig.same_mounts(rig):
                log.warning(
                    "camera mounts differ from the LAC's: rebuilding the localizer with the reported ones"
                )
                self.localizer = self._make_localizer(rig)
        self._ticks += 1
        est = self.estimate = self.localizer.update(
            self.get_mission_time(),
            input_data,
            self.get_imu_data(),
            self.get_linear_speed(),
            self.get_angular_speed(),
        )
        if self._rows is not None:
            x, y, z, roll, pitch, yaw = matrix_to_pose(est.T_map_rover)
            self._rows.write(
                f"{est.mission_time_s:.3f},{x:.4f},{y:.4f},{z:.4f},{roll:.5f},{pitch:.5f},{yaw:.5f},"
                f"{int(est.localized)},{est.fixes}\n"
            )
        self._write_lac_map()
        if self.mapper is not None:  # MAPPER HOOK: per tick, with the pose and the images
            self.mapper.update(est, input_data)
        return VehicleVelocityControl(*self._loop_command(est.T_map_rover))

    def _write_lac_map(self) -> None:
        """lac_map: write the cells that became confident since the last tick (bounded)."""
        if self.localizer.mapper is None or self.get_geometric_map() is None:
            return
        c = time.process_time()
        if self.map_writer is None:
            self.map_writer = LacMapWriter(
                self.localizer.mapper,
                self.get_geometric_map(),
                max_cells_per_step=self.settings["lac_map_cells_per_tick"],
            )
        self.map_writer.step()
        self.map_write_cpu_s.append(time.process_time() - c)

    def _loop_command(self, T_map_rover: np.ndarray) -> tuple[float, float]:
        """(m/s, rad/s): follow the circle about the lander counter-clockwise, steering toward a
        point on it 40 degrees ahead; turn in place when facing far off."""
        p = T_map_rover[:2, 3] - self.lander_xy
        heading = math.atan2(T_map_rover[1, 0], T_map_rover[0, 0])
        a = math.atan2(p[1], p[0]) + math.radians(40)
        target = self.loop_radius_m * np.array([math.cos(a), math.sin(a)]) - p
        err = (math.atan2(target[1], target[0]) - heading + math.pi) % (2 * math.pi) - math.pi
        w = max(-0.5, min(0.5, 1.2 * err))
        v = self.settings["speed_mps"] if abs(err) < math.radians(45) else 0.0
        return v, w

    def finalize(self) -> None:
        est = self.estimate
        if (
            self.localizer is not None
            and self.localizer.mapper is not None
            and self.get_geometric_map() is not None
        ):
            if self.map_writer is None:
                self.map_writer = LacMapWriter(self.localizer.mapper, self.get_geometric_map())
            during, c = self.map_writer.cells_written, time.process_time()
            cells = self.map_writer.finish()
            self.map_finish_cpu_s = time.process_time() - c
            log.info(
                "lunarloc wrote %d cells of the geometric map (%d during the run)", cells, during
            )
        if self.mapper is not None:  # MAPPER HOOK: fill the leaderboard's map
            self.mapper.finalize(self.get_geometric_map())
        if self._rows is not None:
            self._rows.close()
            summary = {
                "ticks": self._ticks,
                "localized": bool(est and est.localized),
                "fixes": est.fixes if est else 0,
                "mission_time_s": est.mission_time_s if est else 0.0,
                "final_T_map_rover": est.T_map_rover.tolist() if est else None,
                "settings": self.settings,
                "lunarloc": lunarloc.__version__,
            }
            (self.output_dir / "summary.json").write_text(json.dumps(summary, indent=1))
        if est is not None:
            log.info(
                "finished at t=%.1f s, localized=%s, %d fixes",
                est.mission_time_s,
                est.localized,
                est.fixes,
            )


def _read_settings(path) -> dict:
    """The TOML settings over the defaults; unknown keys and wrong types are errors."""
    out = dict(DEFAULTS)
    if not path:
        return out
    with open(path, "rb") as fh:
        doc = tomllib.load(fh)
    for key, value in doc.items():
        if key not in DEFAULTS:
            raise ValueError(f"{path}: unknown setting {key!r} (known: {', '.join(DEFAULTS)})")
        want = type(DEFAULTS[key])
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, want) or (want is int and isinstance(value, bool)):
            raise ValueError(f"{path}: {key} must be {want.__name__}, got {value!r}")
        out[key] = value
    if out["lac_map_cells_per_tick"] < 1:
        raise ValueError(
            f"{path}: lac_map_cells_per_tick must be >= 1, got {out['lac_map_cells_per_tick']}"
        )
    if out["odometry"] not in ("visual", "imu"):
        raise ValueError(f"{path}: odometry must be 'visual' or 'imu', got {out['odometry']!r}")
    return out
