"""One multi-session scenario on generated data, end to end: the job behind `lunarloc demo`
and every job of a `lunarloc campaign`.

``run_scenario(config, out)`` reads like its table of contents:

1. simulate a site (``seed``, ``n_rocks``: the LAC's 386 by default) and its renderer;
2. simulate a reference traverse and a vehicle traverse (drifting odometry) of it; with
   ``plan="survey"`` (the default) the reference surveys around the lander and the vehicle
   revisits that ground from another start (:class:`lunarloc.sim.rover.TraversePlan`), as a
   later session of a mission does; ``plan="random"`` drives both from the site's start to
   random waypoints;
3. build the reference map from the reference traverse's images (ground-truth poses, as a
   map surveyed earlier would be);
4. run the online loop on the vehicle traverse against that map and write the run folder;
5. return the run's summary (ATE of odometry and corrected trajectories, fixes, timings).

Each stage that fails raises :class:`ScenarioError` naming the stage. Nothing here prints:
progress goes to the optional ``log`` callable.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Callable

from lunarloc.core.errors import ConfigError, LunarLocError

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "ScenarioConfig",
    "ScenarioError",
    "demo_run_config",
    "run_scenario",
    "scenario_problems",
]


class ScenarioError(LunarLocError):
    """A stage of a scenario failed; the message names the stage."""


# : the longest traverse a scenario simulates (s): `demo --duration`'s cap, the same for campaigns
# and --config
MAX_DURATION_S = 3600.0


@dataclass(frozen=True)
class ScenarioConfig:
    """Everything one scenario depends on. Durations in seconds, rates in Hz, sizes in px."""

    seed: int = 7  # site seed (the vehicle traverse uses traverse index 1, the reference 0)
    n_rocks: int = 386  # rocks on the 27 m x 27 m site (the LAC's density)
    duration_s: float = 90.0  # vehicle traverse
    reference_duration_s: float = 120.0  # reference traverse
    # survey: the reference surveys, the vehicle revisits; random: both drive at random
    plan: str = "survey"
    width: int = 640  # image width; height = 9/16 of it
    image_rate_hz: float = 2.0  # camera rate of both traverses
    sun_elevation_deg: float | None = None  # None: the renderer's default
    sun_azimuth_deg: float | None = None
    min_reference_landmarks: int = 3  # fewer in the reference map is a failed stage
    # The vehicle's odometry source is the run configuration's ``odometry.source`` (one place):
    # :func:`demo_run_config` sets the simulator's drifting record; "visual" or "imu" there for
    # what a LAC rover really has.

    def __post_init__(self) -> None:
        # every value within a documented range (docs/campaign.md), checked before anything runs;
        # booleans are not numbers here (``seed = true`` was seed 1)
        from lunarloc.core.validate import integer, real

        for name, hi in (
            ("duration_s", MAX_DURATION_S),
            ("reference_duration_s", MAX_DURATION_S),
            ("image_rate_hz", 10.0),
        ):
            real(getattr(self, name), name, 0.0, hi, lo_open=True, error=ConfigError)
        integer(self.width, "width", 32, 4096, ConfigError)
        integer(self.n_rocks, "n_rocks", 3, 100_000, ConfigError)
        integer(self.seed, "seed", 0, 2**63 - 1, ConfigError)
        integer(self.min_reference_landmarks, "min_reference_landmarks", 3, 100_000, ConfigError)
        if self.sun_elevation_deg is not None:
            real(
                self.sun_elevation_deg,
                "sun_elevation_deg",
                -90.0,
                90.0,
                unit="deg",
                error=ConfigError,
            )
        if self.sun_azimuth_deg is not None:
            real(
                self.sun_azimuth_deg,
                "sun_azimuth_deg",
                -360.0,
                360.0,
                unit="deg",
                error=ConfigError,
            )
        if self.plan not in ("survey", "random"):
            raise ConfigError(f"plan={self.plan!r} must be 'survey' or 'random'")

    @property
    def height(self) -> int:
        return int(round(self.width * 9 / 16))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ScenarioConfig":
        if not isinstance(d, dict):
            raise ConfigError(f"scenario settings must be a table, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        if "odometry" in d:
            raise ConfigError(
                "scenario.odometry: the odometry source is set in one place, the run "
                f"configuration's odometry.source (move {d['odometry']!r} there)"
            )
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(
                f"unknown scenario setting(s) {unknown}; known: {', '.join(sorted(known))}"
            )
        if not isinstance(d, dict):
            raise ConfigError(f"scenario settings must be a table, got {type(d).__name__}")
        try:
            return cls(**d)
        except TypeError as exc:
            raise ConfigError(f"bad scenario settings: {exc}") from None


class _Stages:
    """Times each stage, logs it, and turns any failure into a ScenarioError naming it."""

    def __init__(self, log_fn: Callable[[str], None] | None):
        self.log = log_fn or (lambda msg: log.info(msg))
        self.seconds: dict[str, float] = {}

    def __call__(self, name: str):
        import contextlib

        @contextlib.contextmanager
        def cm():
            t0 = time.perf_counter()
            self.log(f"{name} ...")
            try:
                yield
            except LunarLocError as exc:
                raise ScenarioError(f"stage '{name}' failed: {exc}") from exc
            except Exception as exc:  # any crash is a failed stage, loudly and by name
                raise ScenarioError(f"stage '{name}' failed: {type(exc).__name__}: {exc}") from exc
            self.seconds[name] = time.perf_counter() - t0
            self.log(f"{name}: done in {self.seconds[name]:.1f} s")

        return cm()


def demo_run_config():
    """The scenario's default :class:`lunarloc.config.run.RunConfig`: the image defaults with the
    simulator's drifting odometry record (``odometry.source = "record:odometry"``) as the
    vehicle's odometry."""
    from lunarloc.config.run import OdometryConfig, RunConfig

    return RunConfig(odometry=OdometryConfig(source="record:odometry"))


def run_scenario(
    config: ScenarioConfig,
    out: str | Path,
    *,
    log: Callable[[str], None] | None = None,
    figures: bool = True,
    run_config=None,
) -> dict:
    """Run one scenario into the folder ``out`` (``out/data`` holds the generated site,
    archives and reference map; ``out`` the run folder of the vehicle traverse). Returns the
    run's summary with ``scenario`` (the config) and ``stage_seconds`` added.

    run_config : :class:`lunarloc.config.run.RunConfig` of the reference map, the loop and the
        vehicle's odometry (``odometry.source``; default :func:`demo_run_config`). The run folder's
        ``config.json`` holds it with a ``scenario`` section: ``lunarloc demo --config`` repeats
        the run."""
    from lunarloc.sim.render import SiteRenderer
    from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse
    from lunarloc.sim.site import SiteConfig
    from lunarloc.io.maps import save_map
    from lunarloc.pipeline.runner import run
    from lunarloc.pipeline.reference import build_reference_map
    from lunarloc.io.runs import write_run
    from lunarloc.pipeline.sources import ArchiveSource

    c = config
    out = Path(out)
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    stage = _Stages(log)
    base = SimulationConfig(
        site=SiteConfig(n_rocks=c.n_rocks),
        image_rate_hz=c.image_rate_hz,
        width=c.width,
        height=c.height,
        cameras=("FrontLeft", "FrontRight"),
        semantic=False,
    )
    sun = {
        k: v
        for k, v in (
            ("sun_elevation_deg", c.sun_elevation_deg),
            ("sun_azimuth_deg", c.sun_azimuth_deg),
        )
        if v is not None
    }
    if sun:
        base = replace(base, render=replace(base.render, **sun))
    ref_rover = veh_rover = base.rover
    if c.plan == "survey":
        ref_rover, veh_rover = (
            replace(base.rover, plan="survey"),
            replace(base.rover, plan="revisit"),
        )
    with stage(f"simulate site (seed {c.seed}, {c.n_rocks} rocks)"):
        site = simulate_site(c.seed, base.site)
        site.write_rocks_csv(data / "rocks.csv")
        renderer = SiteRenderer(site, base.render)
    with stage(
        f"simulate reference traverse ({c.reference_duration_s:g} s, {c.width}x{c.height} front "
        f"pair at {c.image_rate_hz:g} Hz)"
    ):
        ref_arch, _ = simulate_traverse(
            site,
            data / "reference.lac",
            0,
            replace(base, duration_s=c.reference_duration_s, rover=ref_rover),
            renderer=renderer,
        )
    with stage(f"simulate vehicle traverse ({c.duration_s:g} s, drifting odometry)"):
        veh_arch, _ = simulate_traverse(
            site,
            data / "vehicle.lac",
            1,
            replace(base, duration_s=c.duration_s, rover=veh_rover),
            renderer=renderer,
        )
    rc = run_config or demo_run_config()
    with stage("build the reference map from the reference traverse's images"):
        ref = build_reference_map(ref_arch, rc)
        save_map(ref, data / "reference_map.csv")
        stage.log(f"reference map: {len(ref)} landmarks")
        if len(ref) < c.min_reference_landmarks:
            raise ScenarioError(f"the reference map has only {len(ref)} landmarks")
    with stage("online localization of the vehicle traverse"):
        res = run(ArchiveSource(veh_arch, rc.odometry, rc.detector.pairs), ref, rc)
        res.config["scenario"] = c.to_dict()
        figs = None
        if figures:
            from lunarloc.viz import plot_run

            def figs(s):  # before summary.json, which marks a complete run folder
                for p in plot_run(out, summary=s):
                    stage.log(f"wrote {p}")

        summary = write_run(res, out, before_summary=figs)
    summary["scenario"] = c.to_dict()
    summary["stage_seconds"] = {k: round(v, 2) for k, v in stage.seconds.items()}
    return summary


def scenario_problems(summary: dict) -> list[str]:
    """The scenario's acceptance check: at least one fix accepted, and the corrected
    trajectory better than odometry. Empty when it passes."""
    if summary.get("fixes", 0) == 0:
        return ["no localization fix was accepted"]
    odo, cor = summary.get("ate_odometry"), summary.get("ate_corrected")
    if odo and cor and cor["rmse_m"] >= odo["rmse_m"]:
        return ["the corrected trajectory is not better than odometry"]
    return []
