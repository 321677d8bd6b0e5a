"""A minimal game clock (the real one follows CARLA's world snapshots)."""

import datetime


class GameTime:
    _time_s = 0.0
    _delta_s = 0.0
    _frame = 0
    _platform_time_s = 0.0

    @staticmethod
    def restart() -> None:
        GameTime._time_s = GameTime._delta_s = GameTime._platform_time_s = 0.0
        GameTime._frame = 0

    @staticmethod
    def on_tick(delta_s: float, platform_time_s: float) -> None:
        GameTime._frame += 1
        GameTime._delta_s = delta_s
        GameTime._time_s += delta_s
        GameTime._platform_time_s = platform_time_s

    @staticmethod
    def get_time() -> float:
        return GameTime._time_s

    @staticmethod
    def get_delta_time() -> float:
        return GameTime._delta_s

    @staticmethod
    def get_platform_time() -> float:
        return GameTime._platform_time_s

    @staticmethod
    def get_wallclocktime():
        return datetime.datetime.now()

    @staticmethod
    def get_frame() -> int:
        return GameTime._frame
