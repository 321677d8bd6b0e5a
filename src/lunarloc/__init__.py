"""lunarloc: rock-landmark global localization for planetary rovers.

The one-call API::

    from lunarloc import load_map, localize
    result = localize(load_map("reference.csv"), load_map("vehicle.csv"))
    if result.success:
        print(result.T_ref_veh)
"""

import logging

from lunarloc._runtime import ensure_numba_cache_dir

ensure_numba_cache_dir()  # before numba is imported (read-only installs, unwritable $HOME)

from lunarloc.errors import LunarLocError  # noqa: E402
from lunarloc.localize import LocalizationConfig, LocalizationResult, Mode, Solver, localize  # noqa: E402
from lunarloc.maps import AggregationConfig, LandmarkMap, load_map, load_traverse, save_map  # noqa: E402

__version__ = "0.1.0"
__all__ = [
    "AggregationConfig",
    "LandmarkMap",
    "LocalizationConfig",
    "LocalizationResult",
    "LunarLocError",
    "Mode",
    "Solver",
    "load_map",
    "load_traverse",
    "localize",
    "save_map",
]

logging.getLogger(__name__).addHandler(logging.NullHandler())
