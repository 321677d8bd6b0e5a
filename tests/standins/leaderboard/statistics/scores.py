"""The mission scores the leaderboard's statistics manager computes from the agent's map.

* geometric map (300): share of cells whose height is within 0.05 m of the truth;
* rocks (300): F1 of the per-cell rock flags, uncompleted flags counted as False (0 when
  the ground truth has no rock);
* mapping productivity (250): ``min(completed cells / mission time / (total cells /
  max mission time), 1)``, a cell completed when both its height and rock flag are set;
* localization (150): only when the fiducials were not used.
"""

from __future__ import annotations

import numpy as np

from leaderboard.agents.geometric_map import MAP_UNCOMPLETED_VALUE, ROCK_UNCOMPLETED_VALUE


def mission_scores(
    ground_map, agent_map, mission_duration_s: float, fiducials_used: bool, constants
) -> dict:
    out = {"geometric_map": 0.0, "rocks_map": 0.0, "mapping_productivity": 0.0, "localization": 0.0}
    if agent_map is not None and ground_map is not None:
        err_ok = (
            np.abs(ground_map[:, :, 2] - agent_map[:, :, 2]) < constants.geometric_map_threshold
        )
        out["geometric_map"] = (
            constants.geometric_map_max_score * float(np.sum(err_ok)) / err_ok.size
        )
        truth = ground_map[:, :, 3] == 1
        if truth.any():
            rocks = agent_map[:, :, 3].copy()
            rocks[rocks == ROCK_UNCOMPLETED_VALUE] = 0
            flag = rocks == 1
            tp, fp, fn = np.sum(flag & truth), np.sum(flag & ~truth), np.sum(~flag & truth)
            out["rocks_map"] = constants.rock_max_score * 2 * tp / (2 * tp + fp + fn)
    if agent_map is not None:
        done = (agent_map[:, :, 2] != MAP_UNCOMPLETED_VALUE) & (
            agent_map[:, :, 3] != ROCK_UNCOMPLETED_VALUE
        )
        rate = float(np.sum(done)) / mission_duration_s if mission_duration_s else 0.0
        out["mapping_productivity"] = constants.mapping_productivity_max_score * min(
            rate / constants.mapping_productivity_score_rate, 1.0
        )
    out["localization"] = 0.0 if fiducials_used else constants.fiducials_max_score
    out["total"] = sum(out.values())
    return out
