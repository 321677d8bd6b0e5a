"""benchmarks/sim_heldout.py's lighting option: the renderer gets the lighting asked for, the
archive's name carries it (the sun+lamps names stay as they were, so earlier renders are
reused), and an unknown lighting is refused by the argument parser. Nothing is rendered: the
simulator is replaced by a recorder."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import sim_heldout

from lunarloc.sim.render import Lighting


@pytest.fixture
def recorded(monkeypatch):
    import lunarloc.sim.simulate as simulate_mod

    seen = []
    monkeypatch.setattr(simulate_mod, "simulate_site", lambda seed, sc: ("site", seed, sc))
    monkeypatch.setattr(
        simulate_mod,
        "simulate_traverse",
        lambda site, path, index, sc: seen.append((site[1], Path(path), sc)),
    )
    return seen


@pytest.mark.parametrize(
    ("lighting", "tag", "sun", "lamps"),
    [("sun+lamps", "", True, True), ("lamps", "_lamps", False, True), ("sun", "_sun", True, False)],
)
def test_render_passes_the_lighting_and_names_the_archive_after_it(
    tmp_path, recorded, lighting, tag, sun, lamps
):
    p = sim_heldout.render(540, "lac", 60.0, 0.5, tmp_path, lighting)
    el, az = sim_heldout.sun_of(540)
    assert p == tmp_path / f"site540_lac{tag}_el{el:g}_az{az:g}_60s.lac"
    (seed, path, sc) = recorded[0]
    assert seed == 540 and path == p
    r = sc.render
    assert r.lighting == Lighting.parse(lighting)
    assert (r.sun_on, r.lamps_on) == (sun, lamps)
    # the sun recipe is kept whatever the lighting (the renderer ignores it without the sun)
    assert (r.sun_elevation_deg, r.sun_azimuth_deg) == (el, az)
    assert r.terrain_up_normal  # the LAC look
    assert sc.cameras == ("FrontLeft", "FrontRight")


def test_an_existing_archive_is_reused_and_a_bad_lighting_refused(tmp_path, recorded, capsys):
    name = sim_heldout.archive_name(541, "lac", 60.0, "lamps")
    (tmp_path / name).write_bytes(b"")
    assert sim_heldout.render(541, "lac", 60.0, 0.5, tmp_path, "lamps") == tmp_path / name
    assert recorded == []
    # the sun+lamps archive of the same seed is another file
    assert sim_heldout.archive_name(541, "lac", 60.0) != name
    with pytest.raises(SystemExit):
        sim_heldout.main(["--seeds", "541", "--lighting", "moon", "--render-only"])
    assert "--lighting" in capsys.readouterr().err
    assert (
        sim_heldout.main(
            ["--seeds", "541", "--lighting", "lamps", "--render-only", "--out-dir", str(tmp_path)]
        )
        == 0
    )
    assert recorded == []
