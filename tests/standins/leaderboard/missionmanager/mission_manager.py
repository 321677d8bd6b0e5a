"""The mission loop: per tick the world advances, the agent runs (its command applies to the
next world step), the mission clock advances; ``finalize()`` once the mission ends (time up
or ``mission_complete()``). An exception from the agent becomes an AgentRuntimeError."""

from __future__ import annotations

from leaderboard.agents.agent_wrapper import AgentRuntimeError
from leaderboard.utils.timer import GameTime


class MissionManager:
    def __init__(self, world, vehicle, agent_wrapper, max_mission_duration_s: float):
        self._world, self._vehicle, self._wrapper = world, vehicle, agent_wrapper
        self._max_s = float(max_mission_duration_s)
        self.mission_duration_s = 0.0
        self.ticks = 0

    def run(self) -> None:
        GameTime.restart()
        running = True
        while running:
            self._world.tick()
            GameTime.on_tick(self._world.delta_seconds, self._world.platform_time_s)
            try:
                control, components, _ = self._wrapper.tick(self.mission_duration_s)
                self._vehicle.apply_velocity_control(control)
                components.apply_control(self._vehicle)
            except Exception as e:
                raise AgentRuntimeError(e) from e
            self.ticks += 1
            self.mission_duration_s += GameTime.get_delta_time()
            if self.mission_duration_s >= self._max_s or self._wrapper.agent.has_finished():
                self._wrapper.agent.finalize()
                running = False
