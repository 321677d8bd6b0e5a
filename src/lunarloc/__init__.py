"""lunarloc: rock-landmark global localization for planetary rovers.

The per-tick component a rover agent calls (see docs/online-component.md)::

    from lunarloc import OnlineLocalizer, load_reference
    loc = OnlineLocalizer(load_reference("map.csv"), initial_pose=T_map_rover0)
    est = loc.update(mission_time_s, input_data, imu, linear_speed, angular_speed)

The one-call API (what ``lunarloc localize REFERENCE VEHICLE`` does)::

    from lunarloc import load_reference, load_vehicle, localize
    veh = load_vehicle("traverse_5.csv")      # a traverse CSV: its map, path and last position
    result = localize(load_reference("traverse_3.csv"), veh.map, query_xyz=veh.query_xyz,
    path_xyz=veh.path_xyz)
    if result.success:
        print(result.T_ref_veh)

``veh.map`` carries the file's pose provenance (a dataset traverse CSV: ground-truth poses, judged
rigid unless odometry bounds are stated); ``result.odometry_bounds`` says where the bounds came
from.
"""

import logging

from lunarloc.core.runtime import ensure_numba_cache_dir

ensure_numba_cache_dir()  # before numba is imported (read-only installs, unwritable $HOME)

from lunarloc.core.errors import LunarLocError  # noqa: E402
from lunarloc.localization.config import LocalizationConfig, Mode, Solver  # noqa: E402
from lunarloc.localization.result import LocalizationResult  # noqa: E402
from lunarloc.localization.localize import localize  # noqa: E402
from lunarloc.io.maps import (  # noqa: E402
    AggregationConfig,
    LandmarkMap,
    PoseProvenance,
    VehicleInput,
    load_map,
    load_traverse,
    load_vehicle,
    save_map,
)
from lunarloc.io.trajectory import write_kitti, write_tum  # noqa: E402

__version__ = "0.1.0"
__all__ = [
    "AggregationConfig",
    "LandmarkMap",
    "PoseProvenance",
    "LocalizationConfig",
    "LocalizationResult",
    "LunarLocError",
    "Mode",
    "Solver",
    "load_map",
    "load_traverse",
    "load_vehicle",
    "VehicleInput",
    "write_tum",
    "write_kitti",
    "localize",
    "save_map",
    "OnlineLocalizer",
    "OnlineConfig",
    "CameraRig",
    "Estimate",
    "PlaybackAgent",
    "load_reference",
    "LacMapper",
    "LacMapperConfig",
    "write_geometric_map",
    "as_transform_matrix",
    "LacAgentBase",
    "SensorPosition",
    "VehicleVelocityControl",
]

_LAZY = {  # imported on first use: OpenCV and the detector stay out of `import lunarloc`
    "OnlineLocalizer": "lunarloc.online.component",
    "OnlineConfig": "lunarloc.online.component",
    "CameraRig": "lunarloc.online.component",
    "Estimate": "lunarloc.online.component",
    "PlaybackAgent": "lunarloc.io.lac.playback",
    "load_reference": "lunarloc.pipeline.reference",
    "LacMapper": "lunarloc.mapping.lac_map",
    "LacMapperConfig": "lunarloc.mapping.lac_map",
    "write_geometric_map": "lunarloc.mapping.lac_map",
    "as_transform_matrix": "lunarloc.online.component",
    "LacAgentBase": "lunarloc.io.lac.leaderboard",  # the leaderboard's types, mirrored
    "SensorPosition": "lunarloc.io.lac.leaderboard",
    "VehicleVelocityControl": "lunarloc.io.lac.leaderboard",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'lunarloc' has no attribute {name!r}")


logging.getLogger(__name__).addHandler(logging.NullHandler())
