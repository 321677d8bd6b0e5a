"""Synthetic traverse with world-frame rock detections (no images), shared by the loop tests."""

import math

import numpy as np

from lunarloc.io.maps import Traverse


def synthetic_traverse(
    seed: int = 0,
    length_m: float = 30.0,
    rate_hz: float = 20.0,
    speed: float = 0.5,
    noise_m: float = 0.02,
    every: int = 10,
):
    """Rocks (N, 3) and a Traverse driving a zig-zag among them, detections within 5 m
    ahead every `every` frames, with `noise_m` Gaussian noise."""
    rng = np.random.default_rng(seed)
    rocks = np.column_stack(
        [rng.uniform(-10, 25, 500), rng.uniform(-10, 15, 500), rng.uniform(0, 0.2, 500)]
    )
    n = int(length_m / speed * rate_hz)
    heading = 0.0
    pos = np.zeros((n, 3))
    yaw = np.zeros(n)
    for i in range(1, n):
        if i % int(8 / speed * rate_hz) == 0:
            heading += rng.choice([-1, 1]) * 0.9
        yaw[i] = heading
        pos[i] = pos[i - 1] + speed / rate_hz * np.array(
            [math.cos(heading), math.sin(heading), 0.0]
        )
    dets, det_frame = [], []
    for i in range(0, n, every):
        d = rocks - pos[i]
        ahead = d[:, 0] * math.cos(yaw[i]) + d[:, 1] * math.sin(yaw[i])
        vis = (np.linalg.norm(d[:, :2], axis=1) < 5) & (ahead > 0.5)
        if np.any(vis):
            dets.append(rocks[vis] + rng.normal(0, noise_m, (vis.sum(), 3)))
            det_frame.append(np.full(vis.sum(), i + 1))
    trav = Traverse(
        np.arange(1, n + 1), pos, np.concatenate(dets), np.concatenate(det_frame), name="synthetic"
    )
    return rocks, trav
