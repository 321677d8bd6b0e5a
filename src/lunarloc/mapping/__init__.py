"""Maps built from what the rover sees: the LAC geometric map (:mod:`lunarloc.mapping.lac_map`)."""

from lunarloc.mapping.lac_map import LacMapEstimate, LacMapper, LacMapperConfig, write_geometric_map

__all__ = ["LacMapper", "LacMapperConfig", "LacMapEstimate", "write_geometric_map"]
