"""`lunarloc campaign`: spec parsing, job grid, failure recording, resume, and one real job
on a local Dask cluster."""

from __future__ import annotations

import csv
import json

import pytest

from lunarloc.pipeline import campaign as camp
from lunarloc.cli.app import main
from lunarloc.core.errors import FileFormatError
from lunarloc.pipeline.scenario import ScenarioConfig


def _spec(tmp_path, text: str):
    p = tmp_path / "spec.toml"
    p.write_text(text)
    return p


def test_example_spec_is_valid_and_has_eight_stable_jobs(tmp_path, capsys):
    assert main(["campaign", "--example"]) == 0
    text = capsys.readouterr().out
    spec = camp.load_spec(_spec(tmp_path, text))
    jobs = spec.jobs()
    assert len(jobs) == 8
    assert len({j.id for j in jobs}) == 8
    assert [j.id for j in jobs] == [j.id for j in camp.load_spec(_spec(tmp_path, text)).jobs()]
    assert {j.scenario.seed for j in jobs} == {101, 102}


@pytest.mark.parametrize(
    "text, match",
    [
        ("[grid]\nseed = [", "not a valid TOML"),
        ("[grdi]\nseed = [1]", "unknown section"),
        ("[grid]\nseeds = [1]", "unknown scenario setting"),
        ("[grid]\nseed = []", "non-empty list"),
        ("[grid]\nseed = 3", "non-empty list"),
        ("[job]\nwidth = 'abc'", "width"),
        ("[job]\nduration_s = -1.0", "duration_s"),
        ("[job]\nduration_s = nan", "duration_s"),
        ("[grid]\nseed = [1, 1]", "repeats"),
        ("grid = 3", "must be tables"),
    ],
)
def test_bad_specs_are_clear_errors(tmp_path, text, match):
    with pytest.raises(FileFormatError, match=match):
        camp.load_spec(_spec(tmp_path, text))


def test_cli_bad_spec_exits_2_without_traceback(tmp_path, capsys):
    assert (
        main(["campaign", str(_spec(tmp_path, "[grid]\nseed = [")), "-o", str(tmp_path / "o")]) == 2
    )
    err = capsys.readouterr().err
    assert "not a valid TOML" in err and "Traceback" not in err
    assert main(["campaign", str(tmp_path / "missing.toml"), "-o", str(tmp_path / "o")]) == 2


def _fake_summary(cfg: ScenarioConfig) -> dict:
    return {
        "reference_landmarks": 50,
        "vehicle_landmarks": 30,
        "attempts": 4,
        "fixes": 2,
        "ate_odometry": {"rmse_m": 0.2},
        "ate_corrected": {"rmse_m": 0.03 + cfg.seed * 1e-4},
        "final_error_odometry_m": 0.3,
        "final_error_corrected_m": 0.02,
        "max_accepted_fix_error_m": 0.04,
        "real_time_fraction": 0.1,
    }


def test_failed_job_is_recorded_and_rerun_skips_finished_jobs(tmp_path, monkeypatch):
    import lunarloc.pipeline.scenario as scenario

    calls = []

    def fake_run(cfg, out, **kw):
        calls.append(cfg.seed)
        if cfg.seed == 2:
            raise RuntimeError("renderer exploded")
        return _fake_summary(cfg)

    monkeypatch.setattr(scenario, "run_scenario", fake_run)
    spec = camp.CampaignSpec(name="t", job={"width": 320}, grid={"seed": [1, 2, 3]})
    res = camp.run_campaign(spec, tmp_path / "out", scheduler="sync")
    assert sorted(calls) == [1, 2, 3]
    by_seed = {r["seed"]: r for r in res.rows}
    assert by_seed[2]["status"] == "failed" and "renderer exploded" in by_seed[2]["error"]
    assert by_seed[1]["status"] == "ok" and by_seed[1]["check"] == "pass"
    with open(res.table_csv) as fh:
        rows = list(csv.DictReader(fh))
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert float(rows[2]["corrected_rmse_m"]) == pytest.approx(0.0303)
    assert res.figure is not None and res.figure.stat().st_size > 0
    # the rerun only retries the failed job
    calls.clear()
    res2 = camp.run_campaign(spec, tmp_path / "out", scheduler="sync")
    assert calls == [2] and res2.skipped == 2


def test_check_failure_is_a_result_not_a_crash(tmp_path, monkeypatch):
    import lunarloc.pipeline.scenario as scenario

    def no_fix(cfg, out, **kw):
        s = _fake_summary(cfg)
        s["fixes"] = 0
        return s

    monkeypatch.setattr(scenario, "run_scenario", no_fix)
    res = camp.run_campaign(camp.CampaignSpec(grid={"seed": [4]}), tmp_path / "o", scheduler="sync")
    assert res.rows[0]["status"] == "ok" and "no localization fix" in res.rows[0]["check"]
    # not passed: a rerun tries it again only if it failed; a check result is final
    res2 = camp.run_campaign(
        camp.CampaignSpec(grid={"seed": [4]}), tmp_path / "o", scheduler="sync"
    )
    assert res2.skipped == 1


@pytest.mark.slow
def test_real_job_on_a_local_dask_cluster(tmp_path):
    pytest.importorskip("dask.distributed")
    pytest.importorskip("embreex")
    spec = camp.CampaignSpec(
        name="tiny",
        job={"duration_s": 4.0, "reference_duration_s": 12.0, "width": 320, "n_rocks": 1500},
        grid={"seed": [5]},
    )
    res = camp.run_campaign(spec, tmp_path / "o", workers=1)
    assert "local cluster" in res.scheduler
    row = res.rows[0]
    assert row["status"] == "ok", row.get("error")
    out = tmp_path / "o" / "jobs" / row["job"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reference_landmarks"] == row["reference_landmarks"]
    assert (out / "data" / "vehicle.lac").is_file()
