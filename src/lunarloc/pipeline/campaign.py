"""Evaluation campaigns: a grid of scenarios run as Dask tasks.

A campaign spec (TOML) names the settings every job shares (``[job]``) and the axes of
the grid (``[grid]``: every combination is one job); both take the fields of
:class:`lunarloc.pipeline.scenario.ScenarioConfig`::

    [campaign]
    name = "example"
    [job]
    duration_s = 40.0
    width = 320
    [grid]
    seed = [101, 102]
    sun_elevation_deg = [6.0, 25.0]

``run_campaign(spec, out)`` runs every job with :func:`lunarloc.pipeline.scenario.run_scenario`
on a Dask ``distributed`` cluster: a local one (``LocalCluster``, one single-threaded
worker process per core by default) or the cluster whose scheduler address is given
(the same code; the workers need lunarloc installed and ``out`` on a shared file system),
or ``"sync"`` to run them one after another in this process. Each job writes
``out/jobs/<id>/`` and its ``result.json`` last; a rerun skips jobs whose result says
``ok``. A job that fails (raises) is recorded (status ``failed`` with the error), never
fatal; a job that ran has status ``ok`` and its scenario check (:func:`scenario_problems`:
a fix accepted and the corrected trajectory better than odometry) in ``check``.
The table of all jobs is written to ``out/results.csv`` (and ``results.parquet`` when
pandas and pyarrow are installed) with a summary figure ``out/summary.png``.

Dask is an optional dependency (``pip install 'lunarloc[campaign]'``), imported lazily.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import logging
import math
import re
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from lunarloc.core.errors import ConfigError, FileFormatError, OutputError, require
from lunarloc.pipeline.scenario import ScenarioConfig

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = ["CampaignSpec", "Job", "EXAMPLE_SPEC", "load_spec", "run_campaign", "run_job"]

#: Eight small jobs (2 sites x 2 sun elevations x 2 rock densities) that finish in minutes
#: on a 2-core machine; `lunarloc campaign --example` prints it.
EXAMPLE_SPEC = """\
# lunarloc campaign spec: every combination of the [grid] values is one job; [job] holds
# the settings all jobs share. Keys are the fields of lunarloc.pipeline.scenario.ScenarioConfig:
# seed, n_rocks, duration_s, reference_duration_s, width, image_rate_hz,
# sun_elevation_deg, sun_azimuth_deg, min_reference_landmarks, plan. (The odometry source is the run
# configuration's odometry.source; the campaign uses the demo's: the drifting record.)
[campaign]
name = "example"

[job]
duration_s = 60.0
reference_duration_s = 100.0
width = 480
image_rate_hz = 2.0

[grid]
seed = [101, 102]
sun_elevation_deg = [8.0, 20.0]
n_rocks = [386, 800]
"""

RESULT_COLUMNS = [
    "job",
    "status",
    "check",
    "seed",
    "n_rocks",
    "sun_elevation_deg",
    "reference_landmarks",
    "vehicle_landmarks",
    "attempts",
    "fixes",
    "odometry_rmse_m",
    "corrected_rmse_m",
    "final_error_odometry_m",
    "final_error_corrected_m",
    "max_accepted_fix_error_m",
    "real_time_fraction",
    "wall_s",
    "error",
]


#: the most jobs one campaign may hold (checked from the axes' lengths, before the grid is built)
MAX_JOBS = 10_000


@dataclass(frozen=True)
class Job:
    """One cell of the grid: an id (stable across reruns) and its scenario."""

    id: str
    scenario: ScenarioConfig


@dataclass
class CampaignSpec:
    name: str = "campaign"
    job: dict[str, Any] = field(default_factory=dict)
    grid: dict[str, list] = field(default_factory=dict)

    @property
    def size(self) -> int:
        """The number of jobs, from the axes' lengths (the grid is not built)."""
        return math.prod(len(v) for v in self.grid.values())

    def check(self) -> None:
        """Refuse, before any job is built: more than MAX_JOBS combinations (computed from the
        axes), and any value out of range (each axis value merged over ``job`` alone: the
        settings have no cross-field constraints, so every combination is then valid)."""
        n = self.size
        if n > MAX_JOBS:
            axes = " x ".join(f"{len(v)} {k}" for k, v in sorted(self.grid.items()))
            raise ConfigError(f"{n} jobs ({axes}); a campaign is limited to {MAX_JOBS}")
        try:
            ScenarioConfig.from_dict(dict(self.job))
        except ConfigError as exc:
            raise ConfigError(f"[job]: {exc}") from None
        for k, values in sorted(self.grid.items()):
            for i, v in enumerate(values):
                if isinstance(v, (list, dict)):
                    raise ConfigError(
                        f"grid axis '{k}', value {i + 1}: {v!r} is a list or table, not a value"
                    )
                try:
                    ScenarioConfig.from_dict({**self.job, k: v})
                except ConfigError as exc:
                    raise ConfigError(f"grid axis '{k}', value {i + 1}: {exc}") from None

    def jobs(self) -> list[Job]:
        """Every combination of the grid's values, each merged over ``job``; validated."""
        self.check()
        keys = sorted(self.grid)
        combos = itertools.product(*(self.grid[k] for k in keys)) if keys else [()]
        out = []
        for combo in combos:
            settings = {**self.job, **dict(zip(keys, combo))}
            scenario = ScenarioConfig.from_dict(settings)
            out.append(Job(_job_id(dict(zip(keys, combo)), settings), scenario))
        ids = [j.id for j in out]
        if len(set(ids)) != len(ids):
            raise ConfigError("the grid repeats a combination (duplicate values on an axis)")
        return out


def _job_id(axes: dict, settings: dict) -> str:
    """Readable and stable: the grid values, plus a short hash of all settings."""
    slug = "-".join(f"{k.split('_')[0]}{v}" for k, v in sorted(axes.items())) or "job"
    digest = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:6]
    return f"{slug}-{digest}".replace("/", "_").replace(" ", "")


def load_spec(path: str | Path) -> CampaignSpec:
    """Read a campaign spec TOML; errors name the file and what is wrong."""
    try:
        import tomllib
    except ImportError:  # pragma: no cover - python < 3.11
        import tomli as tomllib

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    if path.stat().st_size > 1_000_000:
        raise FileFormatError(f"{path}: a campaign spec over 1 MB is not plausible")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as exc:
        raise FileFormatError(f"{path}: not a valid TOML spec: {exc}") from None
    unknown = sorted(set(doc) - {"campaign", "job", "grid"})
    if unknown:
        raise FileFormatError(
            f"{path}: unknown section(s) {unknown}; expected [campaign], [job], [grid]"
        )
    meta, job, grid = doc.get("campaign", {}), doc.get("job", {}), doc.get("grid", {})
    if not all(isinstance(x, dict) for x in (meta, job, grid)):
        raise FileFormatError(f"{path}: [campaign], [job] and [grid] must be tables")
    for k, v in grid.items():
        if not isinstance(v, list) or not v:
            raise FileFormatError(f"{path}: grid axis '{k}' must be a non-empty list")
    if not job and not grid:
        raise FileFormatError(
            f"{path}: neither [job] nor [grid]: nothing to run (see lunarloc campaign --example)"
        )
    name = meta.get("name", path.stem)
    if not isinstance(name, str):
        raise FileFormatError(f"{path}: [campaign] name must be a string, got {name!r}")
    spec = CampaignSpec(name=name, job=dict(job), grid=dict(grid))
    try:
        # the size and every value checked first (CampaignSpec.check), then the grid built
        spec.jobs()
    except ConfigError as exc:
        raise FileFormatError(f"{path}: {exc}") from None
    return spec


def run_job(job: Job, jobs_dir: str) -> dict:
    """Run one job into ``jobs_dir/<id>`` and return its table row. Never raises: a failure
    is a row with ``status = failed`` and the error. Runs on a Dask worker."""
    from lunarloc.pipeline.scenario import run_scenario, scenario_problems

    out = Path(jobs_dir) / job.id
    t0 = time.perf_counter()
    row: dict[str, Any] = {
        "job": job.id,
        "seed": job.scenario.seed,
        "n_rocks": job.scenario.n_rocks,
        "sun_elevation_deg": job.scenario.sun_elevation_deg,
    }
    try:
        s = run_scenario(job.scenario, out, figures=False)
        problems = scenario_problems(s)
        row.update(
            status="ok",
            check="; ".join(problems) or "pass",
            reference_landmarks=s["reference_landmarks"],
            vehicle_landmarks=s["vehicle_landmarks"],
            attempts=s["attempts"],
            fixes=s["fixes"],
            odometry_rmse_m=s["ate_odometry"]["rmse_m"],
            corrected_rmse_m=s["ate_corrected"]["rmse_m"],
            final_error_odometry_m=s["final_error_odometry_m"],
            final_error_corrected_m=s["final_error_corrected_m"],
            max_accepted_fix_error_m=s["max_accepted_fix_error_m"],
            real_time_fraction=s["real_time_fraction"],
        )
    except Exception as exc:  # a failed job is a row, not the end of the campaign
        row.update(status="failed", error=f"{type(exc).__name__}: {exc}")
        out.mkdir(parents=True, exist_ok=True)
        (out / "error.txt").write_text(traceback.format_exc())
    row["wall_s"] = round(time.perf_counter() - t0, 2)
    out.mkdir(parents=True, exist_ok=True)
    from lunarloc.io.outputs import write_text

    # last and atomically: its presence means finished
    write_text(out / "result.json", json.dumps(row, indent=1))
    return row


def _finished(jobs_dir: Path, job: Job) -> dict | None:
    p = jobs_dir / job.id / "result.json"
    if not p.is_file():
        return None
    try:
        row = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return row if row.get("status") == "ok" else None


@dataclass
class CampaignResult:
    rows: list[dict]
    skipped: int
    wall_s: float
    scheduler: str
    table_csv: Path
    figure: Path | None

    @property
    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in self.rows:
            out[r["status"]] = out.get(r["status"], 0) + 1
        return out


def run_campaign(
    spec: CampaignSpec,
    out: str | Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: Callable[[dict, int, int], None] | None = None,
) -> CampaignResult:
    """Run (or resume) the campaign into ``out``; see the module docstring.

    scheduler : None for a local cluster, ``"sync"`` for one job after another in this
        process, else a Dask scheduler address (``tcp://host:8786``).
    workers : local cluster size (default: the machine's cores).
    progress : called with (row, done, total) after each job.
    """
    out = Path(out)
    jobs = spec.jobs()
    if scheduler not in (None, "sync"):
        # a bad or unreachable address is an input error, before any file
        check_scheduler_address(scheduler)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder")
    jobs_dir = out / "jobs"
    jobs_dir.mkdir(parents=True, exist_ok=True)
    from lunarloc.io.outputs import write_text

    write_text(
        out / "spec.json",
        json.dumps({"name": spec.name, "job": spec.job, "grid": spec.grid}, indent=1),
    )
    rows: dict[str, dict] = {}
    todo = []
    for j in jobs:
        done = _finished(jobs_dir, j)
        if done is not None:
            rows[j.id] = done
        else:
            todo.append(j)
    skipped = len(rows)
    total = len(jobs)
    t0 = time.perf_counter()
    if todo and scheduler == "sync":
        for j in todo:
            rows[j.id] = run_job(j, str(jobs_dir))
            if progress:
                progress(rows[j.id], len(rows), total)
        used = "sync (one after another)"
    elif todo:
        try:
            used = _run_distributed(todo, jobs_dir, rows, total, scheduler, workers, progress)
        except BaseException:
            # interrupted (or the cluster failed): the workers are gone once the cluster is closed,
            # and what they were writing must not stay behind as temporary files
            remove_temporaries(jobs_dir, [j for j in todo if j.id not in rows])
            raise
    else:
        used = "none (all jobs finished earlier)"
    wall = time.perf_counter() - t0
    ordered = [rows[j.id] for j in jobs]
    table = _write_table(ordered, out)
    fig = _summary_figure(ordered, out / "summary.png", spec.name)
    return CampaignResult(ordered, skipped, wall, used, table, fig)


def _is_temporary(p: Path) -> bool:
    """A file an atomic writer had not finished: ``.NAME.tmp-XXXX.SUFFIX`` (lunarloc.io.outputs),
    ``.NAME.XXXX.tmp`` (archives) or ``NAME.tmp`` (job results)."""
    n = p.name
    return n.endswith(".tmp") or (n.startswith(".") and ".tmp" in n)


def remove_temporaries(jobs_dir: Path, jobs: list[Job]) -> int:
    """Remove the temporary files left in the folders of `jobs` (unfinished: a worker was
    stopped mid-write); returns how many."""
    n = 0
    for j in jobs:
        d = Path(jobs_dir) / j.id
        if not d.is_dir():
            continue
        for p in d.rglob("*"):
            if _is_temporary(p) and p.is_file():
                try:
                    p.unlink()
                    n += 1
                except OSError:  # pragma: no cover - already gone, or unwritable
                    pass
    return n


_SCHEDULER_ADDRESS = re.compile(
    r"^(?:(?P<proto>[a-z][a-z0-9+.-]*)://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+)"
    r"(?::(?P<port>[0-9]{1,5}))?/?$"
)
_SCHEDULER_PROTOCOLS = ("tcp", "tls", "ws", "wss", "ucx", "inproc")


def check_scheduler_address(address: str, timeout_s: float = 10.0) -> tuple[str, str, int]:
    """(protocol, host, port) of a Dask scheduler address ``[tcp://]host[:port]`` (port 8786
    by default), after a TCP connection to it succeeded; ConfigError (an input error) for a
    malformed address, an unknown protocol or a scheduler that cannot be reached."""
    import socket

    m = _SCHEDULER_ADDRESS.match(address or "")
    if not m:
        raise ConfigError(
            f"--scheduler {address!r}: not a scheduler address (tcp://HOST:PORT, or 'sync')"
        )
    proto = m["proto"] or "tcp"
    if proto not in _SCHEDULER_PROTOCOLS:
        raise ConfigError(
            f"--scheduler {address!r}: unknown protocol {proto!r} (one of "
            f"{', '.join(_SCHEDULER_PROTOCOLS)})"
        )
    port = int(m["port"] or 8786)
    if not 1 <= port <= 65535:
        raise ConfigError(f"--scheduler {address!r}: port {port} outside 1..65535")
    host = m["host"].strip("[]")
    if proto in ("tcp", "tls", "ws", "wss"):
        try:
            with socket.create_connection((host, port), timeout=timeout_s):
                pass
        except OSError as exc:
            raise ConfigError(
                f"--scheduler {address!r}: cannot connect to {host}:{port} "
                f"({exc.strerror or type(exc).__name__})"
            ) from None
    return proto, host, port


def _run_distributed(todo, jobs_dir, rows, total, scheduler, workers, progress) -> str:
    require("dask.distributed", "campaign", "pip install 'lunarloc[campaign]'")
    from dask.distributed import Client, LocalCluster, as_completed

    # distributed logs every connection at INFO; a campaign's output is its own table
    logging.getLogger("distributed").setLevel(logging.WARNING)
    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="30s")
        except (OSError, TimeoutError, ValueError) as exc:  # reachable, but not a Dask scheduler
            raise ConfigError(
                f"--scheduler {scheduler!r}: no Dask scheduler there ({type(exc).__name__}: {exc})"
            ) from None
        used = f"dask scheduler {scheduler}"
    else:
        import os

        n = workers or os.cpu_count() or 1
        # one single-threaded process per worker: the jobs are CPU-bound numpy/numba/OpenCV
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.WARNING,
        )
        client = Client(cluster)
        used = f"dask local cluster ({n} worker processes)"
    try:
        futures = {
            client.submit(run_job, j, str(jobs_dir), key=f"lunarloc-job-{j.id}", pure=False): j
            for j in todo
        }
        for fut in as_completed(futures):
            j = futures[fut]
            try:
                row = fut.result()
            except Exception as exc:  # the worker itself died (memory, signal)
                row = {
                    "job": j.id,
                    "status": "failed",
                    "error": f"worker: {type(exc).__name__}: {exc}",
                    "seed": j.scenario.seed,
                    "n_rocks": j.scenario.n_rocks,
                    "sun_elevation_deg": j.scenario.sun_elevation_deg,
                }
            rows[j.id] = row
            if progress:
                progress(row, len(rows), total)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return used


def _write_table(rows: list[dict], out: Path) -> Path:
    from lunarloc.io.outputs import atomic_open

    path = out / "results.csv"
    with atomic_open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=RESULT_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") if r.get(k) is not None else "" for k in RESULT_COLUMNS})
    try:  # Parquet where the stack for it is installed; CSV always
        import pandas as pd
        import pyarrow  # noqa: F401

        from lunarloc.io.outputs import atomic_path

        with atomic_path(out / "results.parquet") as tmp:
            pd.DataFrame(rows, columns=RESULT_COLUMNS).to_parquet(tmp)
    except ImportError:
        pass
    return path


def _summary_figure(rows: list[dict], path: Path, title: str) -> Path | None:
    """Odometry vs corrected RMSE per job (failed jobs marked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return None
    names = [r["job"] for r in rows]
    x = range(len(rows))

    def val(r, k):
        v = r.get(k)
        return float(v) * 100 if isinstance(v, (int, float)) and math.isfinite(v) else float("nan")

    fig, ax = plt.subplots(figsize=(max(6.0, 0.7 * len(rows) + 2), 4.2))
    w = 0.4
    ax.bar(
        [i - w / 2 for i in x],
        [val(r, "odometry_rmse_m") for r in rows],
        w,
        label="odometry",
        color="0.65",
    )
    ax.bar(
        [i + w / 2 for i in x],
        [val(r, "corrected_rmse_m") for r in rows],
        w,
        label="corrected",
        color="tab:blue",
    )
    for i, r in enumerate(rows):
        note = (
            r["status"]
            if r["status"] != "ok"
            else ("" if r.get("check") == "pass" else "check failed")
        )
        if note:
            # x in data, y in axes fraction (log axis)
            ax.text(
                i,
                0.03,
                note,
                rotation=90,
                va="bottom",
                ha="center",
                color="tab:red",
                fontsize=8,
                transform=ax.get_xaxis_transform(),
            )
    ax.set_yscale("log")
    ax.set_ylabel("trajectory RMSE (cm, log)")
    ax.set_xticks(list(x))
    ax.set_xticklabels(names, rotation=35, ha="right", fontsize=7)
    ok = sum(r["status"] == "ok" for r in rows)
    passed = sum(r.get("check") == "pass" for r in rows)
    ax.set_title(f"campaign '{title}': {ok}/{len(rows)} jobs ran, {passed} passed the check")
    ax.legend()
    fig.tight_layout()
    from lunarloc.io.outputs import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
