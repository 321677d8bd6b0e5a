"""Issue 33 beyond the corpus (tests/_hostile_surfaces.py, run by tests/test_fuzz.py): the
validation layer's stated tolerances, limits checked before any work (memory bounded),
the same caps from an option and from --config, and outputs that stay atomic when a run or
a campaign is interrupted."""

from __future__ import annotations

import json
import tracemalloc

import _hostile as H
import _hostile_surfaces as S
import numpy as np
import pytest

from lunarloc.cli.app import main
from lunarloc.core import validate
from lunarloc.core.errors import ConfigError, InputError, LunarLocError
from lunarloc.core.geometry import pose_to_matrix

# ----------------------------------------------------------------------------- the validation layer


def test_rigid_transform_tolerance_is_the_stated_one():
    R = pose_to_matrix(1.0, 2.0, 0.3, 0.02, -0.01, 2.0)
    assert (
        validate.rigid_transform(R.astype(np.float32), "T").dtype == np.float64
    )  # float32 round-off passes
    near = R.copy()
    near[:3, :3] *= 1 + 0.2 * validate.RIGID_TOL  # R^T R off by 0.4 tol, det by 0.6 tol: inside
    validate.rigid_transform(near, "T")
    off = R.copy()
    off[:3, :3] *= 1 + 0.6 * validate.RIGID_TOL  # 1.2 tol: outside
    with pytest.raises(InputError, match=r"^T: the rotation block is not a rotation"):
        validate.rigid_transform(off, "T")
    with pytest.raises(InputError, match="reflection"):
        validate.rigid_transform(np.diag([1.0, -1.0, 1.0, 1.0]), "T")
    bottom = R.copy()
    bottom[3, 0] = 1e-6
    with pytest.raises(InputError, match="last row"):
        validate.rigid_transform(bottom, "T")
    with pytest.raises(InputError, match="dtype bool"):
        validate.rigid_transform(np.eye(4, dtype=bool), "T")


def test_numbers_refuse_bools_and_state_the_bound():
    assert validate.real(np.float32(0.25), "v", 0, 1) == 0.25
    for bad in (True, "1", None, [1.0]):
        with pytest.raises(InputError, match="^v must be a number"):
            validate.real(bad, "v")
    with pytest.raises(InputError, match=r"v must be <= 0.98 m/s, got 5"):
        validate.real(5.0, "v", -0.98, 0.98, unit="m/s")
    with pytest.raises(ConfigError, match="n must be an integer"):
        validate.integer(1.0, "n", error=ConfigError)
    assert validate.MAX_LINEAR_SPEED_MPS == pytest.approx(2 * 0.49)
    assert validate.MAX_ANGULAR_SPEED_RADPS == pytest.approx(2 * 4.13)


def test_a_refused_tick_leaves_the_component_as_it_was():
    """Every kind of refusal in the middle of a drive: the estimates after it are those of a
    twin that never saw the bad calls."""
    a, b = S._loc(), S._loc()
    rng = np.random.default_rng(5)
    bad_calls = [
        dict(linear_speed=1e300),
        dict(imu=[1e308] * 6),
        dict(odometry=np.diag([2.0, 2.0, 2.0, 1.0])),
        dict(input_data={"Grayscale": np.zeros((720, 1280), np.uint8)}),
        dict(mission_time_s=1e300),
    ]
    for i in range(40):
        imu = S.IMU_REST + rng.normal(0, 0.01, 6)
        if i % 8 == 3:
            args = {
                "mission_time_s": 0.05 * i,
                "input_data": None,
                "imu": imu,
                "linear_speed": 0.2,
                "angular_speed": 0.1,
                **bad_calls[(i // 8) % len(bad_calls)],
            }
            with pytest.raises(LunarLocError):
                a.update(**args)
        ea = a.update(0.05 * i, None, imu, 0.2, 0.1)
        eb = b.update(0.05 * i, None, imu, 0.2, 0.1)
        assert np.array_equal(ea.T_map_rover, eb.T_map_rover) and np.array_equal(
            ea.covariance, eb.covariance
        )
        assert S.rigid_ok(ea.T_map_rover)


# ----------------------------------------------------------------------------- limits before work


def _peak_mib(fn) -> tuple[float, BaseException | None]:
    tracemalloc.start()
    err = None
    try:
        fn()
    except Exception as exc:  # noqa: BLE001 - the refusal is what is measured
        err = exc
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 1024**2, err


def test_a_huge_campaign_is_refused_from_its_axes_with_bounded_memory(tmp_path):
    from lunarloc.pipeline.campaign import load_spec

    spec = H.write(
        tmp_path,
        "s.toml",
        S.spec_text(
            grid={
                "seed": list(range(1000)),
                "n_rocks": list(range(3, 1003)),
                "sun_azimuth_deg": [float(a) for a in range(1000)],
            }
        ),
    )
    peak, err = _peak_mib(lambda: load_spec(spec))
    assert (
        isinstance(err, LunarLocError)
        and "1000000000 jobs" in str(err)
        and "limited to 10000" in str(err)
    )
    assert peak < 8, (
        f"{peak:.1f} MiB to refuse a 10^9-job grid"
    )  # before: 1.56 GB and still building at 60 s


def test_a_bad_value_deep_in_an_axis_is_refused_before_any_job(tmp_path):
    from lunarloc.pipeline.campaign import load_spec

    spec = H.write(
        tmp_path, "s.toml", S.spec_text(grid={"seed": [1, 2], "sun_elevation_deg": [10.0, 1000.0]})
    )
    with pytest.raises(
        LunarLocError,
        match=r"grid axis 'sun_elevation_deg', value 2: sun_elevation_deg must be <= 90",
    ):
        load_spec(spec)


def test_the_epsilon_cap_is_the_same_from_an_option_and_from_a_config_file(tmp_path, capsys):
    from lunarloc.cli.commands_core import MAX_EPSILON_M
    from lunarloc.config.run import SETTING_LIMITS

    assert SETTING_LIMITS["localization.search.epsilon_m"][1] == MAX_EPSILON_M
    a = H.write(tmp_path, "a.csv", H.map_text())
    c = H.write(tmp_path, "c.json", json.dumps({"localization": {"epsilon_m": 0.31}}))
    assert main(["localize", str(a), str(a), "--epsilon", "0.31"]) == 2
    assert main(["localize", str(a), str(a), "--config", str(c)]) == 2
    err = capsys.readouterr().err
    assert (
        "--epsilon must be <= 0.3 m" in err
        and "localization.search.epsilon_m: 0.31 outside (0, 0.3] m" in err
    )


# ----------------------------------------------------------------------------- atomic outputs


def _run_args(tmp_path, *extra):
    a = H.write(tmp_path, "a.lac", H.lac_bytes(H.lac_members()))
    r = H.write(tmp_path, "b.csv", H.map_text())
    return ["run", str(a), "--reference", str(r), "-o", str(tmp_path / "run"), *extra]


def _leftovers(folder):
    return sorted(p.name for p in folder.rglob("*") if p.is_file())


def test_summary_is_written_after_the_figures(tmp_path, monkeypatch):
    """A signal while the figures are drawn: no summary.json (the mark of a complete run),
    no file of this run, no temporary file."""
    from lunarloc import viz
    from lunarloc.io.outputs import RUN_FILES

    real = viz.plot_run
    seen = {}

    def interrupted(outdir, figdir=None, summary=None):
        seen["summary_on_disk"] = (outdir / "summary.json").exists()
        real(outdir, figdir, summary)  # draws them (a summary passed in, none on disk yet) ...
        raise KeyboardInterrupt  # ... then the signal

    monkeypatch.setattr(viz, "plot_run", interrupted)
    assert main(_run_args(tmp_path)) == 130
    assert seen == {"summary_on_disk": False}
    out = tmp_path / "run"
    assert not [n for n in _leftovers(out) if n in RUN_FILES or ".tmp" in n], _leftovers(out)


def test_interrupted_overwrite_leaves_no_temporary_and_no_partial_run(tmp_path, monkeypatch):
    from lunarloc.io import runs

    assert main(_run_args(tmp_path, "--no-plot")) == 0
    real = runs.write_tum
    calls = []

    def second_interrupted(path, *a, **k):
        calls.append(path.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(path, *a, **k)

    monkeypatch.setattr(runs, "write_tum", second_interrupted)
    assert main(_run_args(tmp_path, "--no-plot", "--overwrite")) == 130
    assert (
        _leftovers(tmp_path / "run") == []
    )  # the old run cleared by --overwrite, nothing of the new one


def test_an_interrupted_campaign_removes_its_workers_temporary_files(tmp_path, monkeypatch):
    """The local cluster's workers are stopped mid-write when the campaign is interrupted: what
    they were writing (.NAME.tmp-*, .vehicle.lac.*.tmp, result.json.tmp) is removed once
    the cluster is closed; finished jobs are left alone."""
    import lunarloc.pipeline.campaign as camp

    spec = camp.load_spec(H.write(tmp_path, "s.toml", S.spec_text(grid={"seed": [1, 2]})))
    jobs = spec.jobs()
    out = tmp_path / "out"

    def interrupted(todo, jobs_dir, rows, total, scheduler, workers, progress):
        done, running = todo
        H.write(jobs_dir / done.id, "result.json", json.dumps({"job": done.id, "status": "ok"}))
        rows[done.id] = {"status": "ok"}
        for name in (".vehicle.lac.abc123.tmp", "run/.trajectory.tmp-xyz.tum", "result.json.tmp"):
            H.write(jobs_dir / running.id, name, "partial")
        H.write(jobs_dir / running.id, "data/rocks.csv", "kept: a finished file")
        raise KeyboardInterrupt

    monkeypatch.setattr(camp, "_run_distributed", interrupted)
    with pytest.raises(KeyboardInterrupt):
        camp.run_campaign(spec, out, scheduler=None)
    assert _leftovers(out / "jobs" / jobs[1].id) == ["rocks.csv"]
    assert _leftovers(out / "jobs" / jobs[0].id) == ["result.json"]


def test_odometry_outputs_need_overwrite_and_are_complete(tmp_path, capsys):
    a = H.write(tmp_path, "a.lac", H.lac_bytes(H.lac_members()))
    tum = H.write(tmp_path, "o.tum", "old\n")
    assert main(["odometry", str(a), "-o", str(tum)]) == 2
    assert tum.read_text() == "old\n" and "pass --overwrite" in capsys.readouterr().err
    assert (
        main(
            ["odometry", str(a), "-o", str(tum), "--json", str(tmp_path / "o.json"), "--overwrite"]
        )
        == 0
    )
    assert len(tum.read_text().splitlines()) == 21
    d = json.loads((tmp_path / "o.json").read_text())
    assert all(np.isfinite(v) for v in d.values() if isinstance(v, float))


def test_a_campaign_at_the_limits_is_accepted(tmp_path):
    """The checks refuse what is out of range, not what is at the edge: 10,000 jobs, and every
    setting at its stated bound."""
    from lunarloc.pipeline.campaign import MAX_JOBS, load_spec

    spec = H.write(
        tmp_path,
        "s.toml",
        S.spec_text(
            {
                "duration_s": 3600.0,
                "reference_duration_s": 3600.0,
                "image_rate_hz": 10.0,
                "width": 4096,
                "sun_azimuth_deg": -360.0,
                "min_reference_landmarks": 100_000,
            },
            grid={
                "seed": list(range(100)),
                "n_rocks": list(range(3, 103)),
                "sun_elevation_deg": [90.0],
            },
        ),
    )
    s = load_spec(spec)
    assert s.size == MAX_JOBS and len(s.jobs()) == MAX_JOBS
