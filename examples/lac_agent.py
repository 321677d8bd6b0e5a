"""A Lunar Autonomy Challenge agent that localizes against a reference rock map with lunarloc.

The LAC calls ``setup`` once, ``sensors``/``use_fiducials`` to configure the rover, then
``run_step(input_data)`` every 20 Hz tick (camera images every other tick) and ``finalize``
at the end. In the leaderboard this class would subclass ``leaderboard.autoagents.
autonomous_agent.AutonomousAgent``, which provides the ``get_*`` methods; here they come
from ``self.env``, any object with the same methods (the simulator's agent base, or
:class:`lunarloc.PlaybackAgent` replaying a recording, as in ``tests/test_online_component.py``)::

    from lunarloc import PlaybackAgent
    env = PlaybackAgent("traverse.lac")
    agent = LunarLocAgent(env, "rocks.csv")
    agent.setup()
    while True:
        agent.run_step(env.input_data())
        if env.at_end():
            break
        env.step_frame()
    agent.finalize()

Driving is not this example's subject: ``run_step`` returns a constant gentle command
(a real agent plans here with ``self.estimate.T_map_rover``).
"""

from __future__ import annotations

import collections
import logging

from lunarloc import CameraRig, OnlineLocalizer, load_reference

log = logging.getLogger(__name__)

CAMERAS = ("FrontLeft", "FrontRight")


class LunarLocAgent:
    """LAC agent interface (``setup``, ``use_fiducials``, ``sensors``, ``run_step``, ``finalize``)."""

    def __init__(self, env, reference_path: str, width: int = 1280, height: int = 720):
        self.env = env  # provides get_mission_time(), get_imu_data(), ... (the LAC agent base class)
        self.reference_path = reference_path
        self.width, self.height = width, height
        self.localizer: OnlineLocalizer | None = None
        self.estimate = None
        self.poses = collections.deque(maxlen=1200)  # (mission time s, T_map_rover) of the last minute: bounded

    # -- configuration ----------------------------------------------------------------------
    def use_fiducials(self) -> bool:
        return False  # the localization score counts only without fiducials

    def sensors(self) -> dict:
        return {name: {"camera_active": True, "light_intensity": 1.0, "width": self.width, "height": self.height,
                       "use_semantic": False} for name in CAMERAS}  # fmt: skip

    def setup(self, path_to_conf_file: str | None = None) -> None:
        env = self.env
        rig = CameraRig.from_sensors(self.sensors(), {c: env.get_camera_position(c) for c in CAMERAS})
        self.localizer = OnlineLocalizer(load_reference(self.reference_path), env.get_initial_position(), rig=rig,
                                         lander_pose=env.get_initial_lander_position())  # no rock fixes on the lander
        self.localizer.warm_up()  # before the mission clock matters

    # -- every tick ---------------------------------------------------------------------------
    def run_step(self, input_data: dict):
        env = self.env
        self.estimate = self.localizer.update(env.get_mission_time(), input_data, env.get_imu_data(),
                                              env.get_linear_speed(), env.get_angular_speed())  # fmt: skip
        self.poses.append((self.estimate.mission_time_s, self.estimate.T_map_rover))
        return (0.2, 0.0)  # VehicleVelocityControl(linear m/s, angular rad/s) in the LAC

    def finalize(self) -> None:
        if self.estimate is not None:
            log.info("finished at t=%.1f s, localized=%s, %d fixes", self.estimate.mission_time_s,
                     self.estimate.localized, self.estimate.fixes)  # fmt: skip
