"""Repeatability figures (lunarloc.sim.repeatability): which rock a detection lies on, the
spread of a rock's sightings in a session and the offset between sessions, by radius band."""

import numpy as np
import pytest

from lunarloc.core.errors import InputError
from lunarloc.sim.render import SEM_GROUND, SEM_ROCK_OFFSET
from lunarloc.sim.repeatability import SightingLog, rock_under, summarise


def test_rock_under_takes_the_majority_rock_of_the_window():
    sem = np.full((40, 40), SEM_GROUND, np.uint16)
    sem[10:20, 10:20] = SEM_ROCK_OFFSET + 7
    sem[10:20, 20:23] = SEM_ROCK_OFFSET + 9
    assert rock_under(sem, (15, 15)) == 7
    assert rock_under(sem, (18.4, 15)) == 7  # 7 covers more of the 7x7 window than 9
    assert rock_under(sem, (22, 15)) == 9  # and here 9 does
    assert rock_under(sem, (30, 30)) == -1  # ground
    assert (
        rock_under(sem, (20, 9)) == -1
    )  # on the rock's edge: rocks cover less than half the window
    assert rock_under(sem, (0, 0)) == -1  # the window is clipped at the border
    with pytest.raises(InputError):
        rock_under(sem[None], (1, 1))


def test_spread_and_session_offset_by_band():
    rng = np.random.default_rng(0)
    log = SightingLog()
    radii = {1: 0.15, 2: 0.3, 3: 0.04, 4: 0.2}
    truth = {1: (1.0, 2.0), 2: (-3.0, 0.5), 3: (0.0, 0.0), 4: (5.0, 5.0)}
    sigma = {1: 0.01, 2: 0.02, 3: 0.05, 4: 0.01}
    shift = {"A": np.zeros(2), "B": np.array([0.03, -0.04])}  # session B places every rock 5 cm off
    for session in ("A", "B"):
        for rock in (1, 2, 3):
            for _ in range(400):
                log.add(
                    session,
                    rock,
                    np.asarray(truth[rock]) + shift[session] + rng.normal(0, sigma[rock], 2),
                )
    log.add("A", 4, (5.0, 5.0))  # too few sightings: left out
    log.add("A", 4, (5.1, 5.0))
    s = summarise(log, radii, min_sightings=3)
    # a 2D normal's distance from its mean: Rayleigh, median sigma * sqrt(2 ln 2)
    med = np.sqrt(2 * np.log(2))
    assert s["0.1-0.2"]["sighting_deviation"]["median_m"] == pytest.approx(0.01 * med, rel=0.1)
    assert s["0.2-0.4"]["sighting_deviation"]["median_m"] == pytest.approx(0.02 * med, rel=0.1)
    assert s["0.025-0.05"]["rock_spread"]["median_m"] == pytest.approx(0.05 * np.sqrt(2), rel=0.1)
    assert s["0.1-0.2"]["rock_spread"]["n"] == 2  # rock 1 in two sessions; rock 4 left out
    assert s["r>=0.1"]["rock_spread"]["n"] == 4
    assert s["r>=0.1"]["sighting_deviation"]["n"] == 1600
    for band in ("0.1-0.2", "0.2-0.4", "0.025-0.05"):
        assert s[band]["session_offset"]["n"] == 1
        assert s[band]["session_offset"]["median_m"] == pytest.approx(0.05, abs=0.01)
    assert s[">=0.4"]["rock_spread"]["n"] == 0 and np.isnan(s[">=0.4"]["rock_spread"]["median_m"])
    assert s["0.05-0.1"]["session_offset"]["n"] == 0


def test_bad_input_is_refused():
    log = SightingLog()
    with pytest.raises(InputError):
        log.add("A", 1, (np.nan, 0.0))
    with pytest.raises(InputError):
        summarise(log, {}, min_sightings=1)
    assert summarise(log, {})["r>=0.1"]["rock_spread"]["n"] == 0
