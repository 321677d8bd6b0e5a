"""How the leaderboard loads, configures and ticks an agent file.

* Loading: the file's directory goes on ``sys.path``, the module is imported by the file's
  base name (up to the first dot), ``get_entry_point()`` returns the class *name*, the
  class is called with no arguments, ``use_fiducials()`` must return a bool. Any failure
  there is an :class:`AgentSetupError`.
* ``setup(vehicle, lander, constants)``: the geometric map, the initial rover pose
  (right-handed, world frame) and the lander pose relative to the rover are set, then
  ``agent.setup(path_to_conf_file)`` runs: no vehicle status exists yet. Failures there are
  an :class:`AgentSetupError` too. Then the sensors: ``agent.sensors()`` must hold every
  ``carla.SensorPosition`` with ``camera_active``, ``light_intensity``, ``width``, ``height``
  (``use_semantic`` optional; refused in evaluation); sizes above 2448 x 2048 are clamped.
* ``tick(mission_time)``: camera data, the IMU, a fresh vehicle status, ``agent(...)``; the
  agent's camera on/off requests are applied afterwards.
"""

from __future__ import annotations

import importlib
import os
import sys

import carla
from leaderboard.agents.agent_utilities import VehicleStatus
from leaderboard.agents.coordinate_conversion import get_lander_transform, toRHCStransform
from leaderboard.agents.geometric_map import GeometricMap
from leaderboard.agents.imu import IMU
from leaderboard.agents.sensor_interface import SensorInterface

MAX_CAMERA_WIDTH = 2448
MAX_CAMERA_HEIGHT = 2048


class AgentSetupError(Exception):
    pass


class AgentRuntimeError(Exception):
    pass


class SensorConfigurationError(Exception):
    pass


def _get_agent_instance(agent_filename: str):
    module_name = os.path.basename(agent_filename).split(".")[0]
    sys.path.insert(0, os.path.dirname(agent_filename))
    module = importlib.import_module(module_name)
    class_name = getattr(module, "get_entry_point")()
    return getattr(module, class_name)()


class AgentWrapper:
    def __init__(self, world, agent_filename: str, agent_config: str, evaluation: bool):
        self._world = world
        self._vehicle = None
        self._sensor_interface = SensorInterface()
        self.agent = None
        self.agent_fiducials = None
        try:
            self.agent = _get_agent_instance(agent_filename)
            self.agent_fiducials = self.agent.use_fiducials()
            assert isinstance(self.agent_fiducials, bool)
        except Exception as e:
            raise AgentSetupError(e) from e
        self._agent_config = agent_config
        self._evaluation = evaluation
        self._cameras = {"Grayscale": {}, "Semantic": {}}  # pos: [(width, height), active]
        self._imu = None

    def setup(self, vehicle, lander, constants) -> None:
        self._vehicle = vehicle
        try:
            self.agent.set_geometric_map(GeometricMap(constants))
            self.agent.set_initial_position(toRHCStransform(vehicle.get_transform()))
            self.agent.set_initial_lander_position(
                get_lander_transform(vehicle.get_transform(), lander.get_transform())
            )
            self.agent.setup(self._agent_config)
        except Exception as e:
            raise AgentSetupError(e) from e
        self._setup_sensors()

    @staticmethod
    def _check_attributes(sensor_data, p) -> None:
        if p not in sensor_data:
            raise AgentSetupError(
                f"Couldn't find the 'carla.SensorPosition.{p}' in the sensors configuration"
            )
        for key in ("camera_active", "light_intensity", "width", "height"):
            if key not in sensor_data[p]:
                raise AgentSetupError(
                    f"Attribute '{key}' is missing from the sensor 'carla.SensorPosition.{p}'"
                )

    def _setup_sensors(self) -> None:
        self._imu = IMU(self._vehicle)
        sensor_data = self.agent.sensors()
        for p in carla.SensorPosition:
            self._check_attributes(sensor_data, p)
            c = sensor_data[p]
            width = min(int(str(c["width"])), MAX_CAMERA_WIDTH)
            height = min(int(str(c["height"])), MAX_CAMERA_HEIGHT)
            semantic = c.get("use_semantic", False)
            if semantic and self._evaluation:
                raise SensorConfigurationError(
                    "Detected semantic segmentation cameras during the evaluation"
                )
            self._cameras["Grayscale"][p] = [(width, height), False]
            if semantic:
                self._cameras["Semantic"][p] = [(width, height), False]
            self._vehicle.set_camera_state(p, c["camera_active"])
            self._vehicle.set_light_state(p, c["light_intensity"])
            if c["camera_active"]:
                self._activate_camera(p)
        for _ in range(2):  # the leaderboard ticks the world twice before the mission
            self._world.tick()

    def _activate_camera(self, p) -> None:
        if self._cameras["Grayscale"][p][1]:
            return
        self._cameras["Grayscale"][p][1] = True
        if p in self._cameras["Semantic"]:
            self._cameras["Semantic"][p][1] = True

    def _deactivate_camera(self, p) -> None:
        if not self._cameras["Grayscale"][p][1]:
            return
        self._cameras["Grayscale"][p][1] = False
        if p in self._cameras["Semantic"]:
            self._cameras["Semantic"][p][1] = False

    def tick(self, mission_time):
        sensor_data = self._sensor_interface.get_data(self._world, self._cameras)
        self.agent.set_imu_data(self._imu.get_data())
        status = VehicleStatus.from_vehicle(self._vehicle, self._evaluation)
        velocity_control, component_control = self.agent(mission_time, status, sensor_data)
        for p, (camera_state, _) in component_control.sensor_state.items():
            if camera_state is not None:
                self._activate_camera(p) if camera_state else self._deactivate_camera(p)
        return velocity_control, component_control, status

    def get_agent_map(self):
        return self.agent.get_map_array()
