"""Camera data per tick, as the leaderboard's sensor interface delivers it.

Cameras run at 10 Hz on the 20 Hz tick: the first agent tick has no images, the next has
all, and so on. ``input_data = {'Grayscale': {SensorPosition: image or None}, 'Semantic':
{...}}`` holds only active cameras (semantic only for cameras configured with it). CARLA
hands a BGRA buffer; grayscale is its ``[:, :, 0]`` (a non-contiguous (H, W) uint8 view),
semantic its ``[:, :, :3]``.
"""

from __future__ import annotations


class SensorReceivedNoData(Exception):
    pass


class SensorInterface:
    def __init__(self):
        self._images_this_tick = False  # toggles every tick; the first tick has none

    def get_data(self, world, cameras: dict) -> dict:
        """cameras: {'Grayscale': {pos: [config, active]}, 'Semantic': {pos: [config, active]}}."""
        data = {"Grayscale": {}, "Semantic": {}}
        active = [p for p, (_, on) in cameras["Grayscale"].items() if on]
        for p in active:
            data["Grayscale"][p] = None
            if p in cameras["Semantic"]:
                data["Semantic"][p] = None
        if self._images_this_tick and active:
            shots = world.capture(
                {p: cameras["Grayscale"][p][0] for p in active},
                semantic={p for p in active if p in cameras["Semantic"]},
            )
            for p, (bgra, sem_bgra) in shots.items():
                data["Grayscale"][p] = bgra[:, :, 0]
                if sem_bgra is not None and p in data["Semantic"]:
                    data["Semantic"][p] = sem_bgra[:, :, :3]
        self._images_this_tick = not self._images_this_tick
        return data
