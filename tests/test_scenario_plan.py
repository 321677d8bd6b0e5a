"""The demo's scenario: LAC density, and a reference that surveys ground the vehicle revisits."""

import pytest

from lunarloc.sim.rover import TraversePlan
from lunarloc.core.errors import ConfigError
from lunarloc.pipeline.scenario import ScenarioConfig, ScenarioError, run_scenario


def test_defaults_are_the_lac_density_and_a_survey():
    c = ScenarioConfig()
    assert c.n_rocks == 386 and c.plan == "survey"
    assert ScenarioConfig.from_dict(c.to_dict()) == c
    with pytest.raises(ConfigError, match="plan"):
        ScenarioConfig(plan="zigzag")


@pytest.mark.parametrize(
    "plan, expected", [("survey", ["survey", "revisit"]), ("random", ["random", "random"])]
)
def test_reference_and_vehicle_plans(monkeypatch, tmp_path, plan, expected):
    import lunarloc.sim.render as render
    import lunarloc.sim.simulate as sim

    seen = []

    def fake_traverse(
        site, path, index, cfg, renderer=None
    ):  # records the plan; stops at the vehicle
        seen.append(TraversePlan.parse(cfg.rover.plan).value)
        if len(seen) == 2:
            raise RuntimeError("stop here")
        return path, None

    monkeypatch.setattr(sim, "simulate_traverse", fake_traverse)
    monkeypatch.setattr(render, "SiteRenderer", lambda *a, **k: None)
    with pytest.raises(ScenarioError, match="vehicle traverse"):
        run_scenario(ScenarioConfig(plan=plan, n_rocks=30), tmp_path, figures=False)
    assert seen == expected
