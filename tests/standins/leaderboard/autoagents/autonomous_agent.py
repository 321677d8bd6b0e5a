"""The base class every LAC agent derives from (``leaderboard.autoagents.autonomous_agent``).

The leaderboard builds the agent with no arguments, calls the setters, then ``setup``;
``__call__`` runs once per 20 Hz tick. The getters read the per-tick vehicle status, which
does not exist before the first tick: ``get_camera_position`` & co. then fail
(``AttributeError`` on None), ``get_imu_data`` too (set by the wrapper each tick).
"""

from __future__ import annotations

import carla
from leaderboard.agents.agent_utilities import AgentComponentsControl
from leaderboard.utils.timer import GameTime

MAX_LINEAR_SPEED = 0.49  # m/s
MAX_ANGULAR_SPEED = 4.13  # rad/s


class AutonomousAgent:
    def __init__(self):
        self._components_control = None
        self._vehicle_status = None
        self._finished = False
        self._geometric_map = None
        self._initial_position = None
        self._initial_lander_position = None
        self._mission_time = 0

    def __call__(self, mission_time, vehicle_status, input_data):
        self._mission_time = mission_time
        self._vehicle_status = vehicle_status
        print(
            f"=== [Agent] -- Wallclock = {str(GameTime.get_wallclocktime())[:-3]} -- System time = "
            f"{GameTime.get_platform_time():.3f} -- Simulation time = {GameTime.get_time():.3f}"
        )  # as the real one does
        self._components_control = AgentComponentsControl()
        control = self.run_step(input_data)
        assert isinstance(control, carla.VehicleVelocityControl)
        out = carla.VehicleVelocityControl()
        out.linear_target_velocity = max(
            min(control.linear_target_velocity, MAX_LINEAR_SPEED), -MAX_LINEAR_SPEED
        )
        out.angular_target_velocity = max(
            min(control.angular_target_velocity, MAX_ANGULAR_SPEED), -MAX_ANGULAR_SPEED
        )
        out.angular_target_velocity *= -1  # into CARLA's left-handed frame
        return out, self._components_control

    # -- set by the leaderboard
    def set_geometric_map(self, geometric_map):
        self._geometric_map = geometric_map

    def set_initial_position(self, position):
        self._initial_position = position

    def set_initial_lander_position(self, position):
        self._initial_lander_position = position

    def set_imu_data(self, imu_data):
        self._imu_data = imu_data

    def has_finished(self):
        return self._finished

    def get_map_array(self):
        return None if self._geometric_map is None else self._geometric_map.get_map_array()

    # -- to override
    def setup(self, path_to_conf_file):
        pass

    def use_fiducials(self):
        return True

    def sensors(self):
        return {
            p: {
                "camera_active": False,
                "light_intensity": 0,
                "width": "2448",
                "height": "2048",
                "use_semantic": False,
            }
            for p in carla.SensorPosition
        }

    def run_step(self, input_data):
        return carla.VehicleVelocityControl()

    def finalize(self):
        pass

    # -- getters
    def get_initial_position(self):
        return self._initial_position

    def get_initial_lander_position(self):
        return self._initial_lander_position

    def get_geometric_map(self):
        return self._geometric_map

    def get_mission_time(self):
        return self._mission_time

    def get_current_power(self):
        return self._vehicle_status.current_power

    def get_consumed_power(self):
        return self._vehicle_status.consumed_power

    def get_imu_data(self):
        return self._imu_data

    def mission_complete(self):
        self._finished = True

    # -- vehicle setters (valid inside run_step)
    def set_front_arm_angle(self, angle):
        self._components_control.front_arm_angle = angle

    def set_back_arm_angle(self, angle):
        self._components_control.back_arm_angle = angle

    def set_front_drums_target_speed(self, speed):
        self._components_control.front_drum_speed = speed

    def set_back_drums_target_speed(self, speed):
        self._components_control.back_drum_speed = speed

    def set_radiator_cover_state(self, radiator_state):
        self._components_control.radiator_cover_state = radiator_state

    def set_light_state(self, light, light_state):
        self._components_control.sensor_state[light][1] = light_state

    def set_camera_state(self, camera, camera_state):
        self._components_control.sensor_state[camera][0] = camera_state

    # -- vehicle getters
    def get_linear_speed(self):
        return self._vehicle_status.odometry_linear_speed

    def get_angular_speed(self):
        return self._vehicle_status.odometry_angular_speed

    def get_front_arm_angle(self):
        return self._vehicle_status.front_arm_angle

    def get_back_arm_angle(self):
        return self._vehicle_status.back_arm_angle

    def get_front_drums_speed(self):
        return self._vehicle_status.front_drums_speed

    def get_back_drums_speed(self):
        return self._vehicle_status.back_drums_speed

    def get_radiator_cover_angle(self):
        return self._vehicle_status.radiator_cover_angle

    def get_light_state(self, light):
        return self._vehicle_status.sensor_state[light][1]

    def get_camera_state(self, camera):
        return self._vehicle_status.sensor_state[camera][0]

    def get_camera_position(self, camera):
        """The camera's pose in the rover frame (right-handed Transform)."""
        return self._vehicle_status.sensor_state[camera][2]

    def get_light_position(self, light):
        return self._vehicle_status.sensor_state[light][3]

    def get_transform(self):
        """The rover's true pose: training only, None in evaluation."""
        return self._vehicle_status.transform
