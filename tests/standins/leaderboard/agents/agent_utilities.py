"""What passes between the leaderboard and the agent each tick: the components control an
agent's setters fill, and the vehicle status its getters read."""

from __future__ import annotations

import carla

from leaderboard.agents.coordinate_conversion import toRHCStransform


class AgentComponentsControl:
    def __init__(self):
        self.front_arm_angle = None
        self.back_arm_angle = None
        self.front_drum_speed = None
        self.back_drum_speed = None
        self.radiator_cover_state = None
        self.sensor_state = {
            p: [None, None] for p in carla.SensorPosition
        }  # [camera on/off, light intensity]

    def apply_control(self, vehicle) -> None:
        for p, (camera_state, light_state) in self.sensor_state.items():
            if light_state is not None:
                vehicle.set_light_state(p, light_state)
            if camera_state is not None:
                vehicle.set_camera_state(p, camera_state)


class VehicleStatus:
    """Built fresh every tick; ``transform`` stays None in evaluation."""

    def __init__(self):
        self.odometry_linear_speed = None
        self.odometry_angular_speed = None
        self.front_arm_angle = None
        self.back_arm_angle = None
        self.front_drums_speed = None
        self.back_drums_speed = None
        self.radiator_cover_angle = None
        self.current_power = None
        self.consumed_power = None
        self.transform = None
        self.sensor_state = {p: [None, None] for p in carla.SensorPosition}

    @staticmethod
    def from_vehicle(vehicle, evaluation: bool) -> VehicleStatus:
        s = VehicleStatus()
        s.odometry_linear_speed = vehicle.get_odometry_speed()
        s.odometry_angular_speed = vehicle.get_odometry_angular_speed()
        s.front_arm_angle = vehicle.get_front_arm_angle()
        s.back_arm_angle = vehicle.get_back_arm_angle()
        s.front_drums_speed = vehicle.get_front_drums_speed()
        s.back_drums_speed = vehicle.get_back_drums_speed()
        s.radiator_cover_angle = vehicle.get_radiator_cover_angle()
        s.current_power = vehicle.get_current_power()
        s.consumed_power = vehicle.get_consumed_power()
        if not evaluation:
            s.transform = toRHCStransform(vehicle.get_transform())
        for p in (
            carla.SensorPosition
        ):  # [camera state, light state, camera pose, light pose] (rover frame)
            s.sensor_state[p] = [
                vehicle.get_camera_state(p),
                vehicle.get_light_state(p),
                toRHCStransform(vehicle.get_camera_relative_transform(p)),
                toRHCStransform(vehicle.get_light_relative_transform(p)),
            ]
        return s
