"""Stand-in of the Lunar Autonomy Challenge leaderboard package (``leaderboard``), written for
lunarloc's tests from the public leaderboard's behaviour (the copy LAC teams vendor, e.g.
``Robaire/MAPLE`` ``leaderboard/leaderboard/``). No leaderboard code is copied; module and
class names mirror the real import paths so that an agent file written for the leaderboard
(``from leaderboard.autoagents.autonomous_agent import AutonomousAgent``, ``import carla``)
loads against these stand-ins when ``tests/standins`` is on ``sys.path``.

What is reproduced, and why it matters to an agent:

* :mod:`leaderboard.agents.agent_wrapper`: the agent file is imported by its base name, its
  ``get_entry_point()`` names the class, which is built with no arguments;
  ``use_fiducials()`` must return a bool; ``setup(path_to_conf_file)`` runs before any vehicle
  status exists (the camera getters fail there); ``sensors()`` must name all eight
  ``carla.SensorPosition`` members with ``camera_active``, ``light_intensity``, ``width``,
  ``height`` (``AgentSetupError`` otherwise); semantic cameras are refused in evaluation.
* :mod:`leaderboard.agents.sensor_interface`: cameras deliver at 10 Hz on the 20 Hz tick,
  the first tick without images; active cameras only, ``None`` without an image; grayscale is
  the ``[:, :, 0]`` view of a BGRA buffer (non-contiguous), semantic ``[:, :, :3]``.
* :mod:`leaderboard.autoagents.autonomous_agent`: ``__call__`` stores the status, calls
  ``run_step`` and asserts a ``carla.VehicleVelocityControl``; clamps to 0.49 m/s and
  4.13 rad/s and flips the angular sign into CARLA's left-handed frame; the getters.
* :mod:`leaderboard.agents.coordinate_conversion`: the right-handed ``Transform`` an agent
  sees (``location.x/y/z`` metres, ``rotation.roll/pitch/yaw`` radians, no matrix method).
* :mod:`leaderboard.agents.imu`: the IMU from finite differences of the true pose at 20 Hz:
  world-frame angular velocity, body-frame specific force, gravity on the first two ticks.
* :mod:`leaderboard.agents.geometric_map`: the 180 x 180 map (27 m, 0.15 m cells) with its
  setters and getters; uncompleted cells hold -inf.
* :mod:`leaderboard.statistics.scores`: the map scores (geometric, rocks, productivity,
  localization) as the statistics manager computes them.
"""
