"""The second hostile corpus (issue 33): the surfaces beyond the first corpus's files and
options -- the per-tick ``OnlineLocalizer`` API an agent calls, campaign specs, ``--config``
files, ``score``, ``odometry`` and archives damaged after writing. Shared, through
:func:`_hostile.corpus`, by ``tests/test_fuzz.py`` and ``benchmarks/hostile_inputs.py``.

CLI cases are :class:`_hostile.Case` as before. API cases carry ``call(folder)``: it returns
what the API returned, or raises. :func:`_hostile.run_case` counts a ``LunarLocError`` whose
message names the argument (``Case.names``) as a clear error only when the component's state
is unchanged: each update case drives two identical localizers, makes the hostile call on one,
then one good tick on both, and the two estimates must agree (:class:`StateChanged` otherwise).
A returned result is checked (``check``): every pose rigid, finite and near the rover.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import _hostile as H
import numpy as np
from _hostile import Case

IMU_REST = [0.0, 0.0, 1.622, 0.0, 0.0, 0.0]


class StateChanged(AssertionError):
    """A refused call left the component in another state than before it."""


# ----------------------------------------------------------------------------- API helpers


def _ref():
    from lunarloc.io.maps import LandmarkMap

    return LandmarkMap(H.rocks(40))


def _small_rig():
    from lunarloc.online.component import CameraRig

    return CameraRig.from_calibration(160, 90, fx=114.25)


def _loc(initial_pose=None, **kw):
    from lunarloc.online.component import OnlineLocalizer

    return OnlineLocalizer(_ref(), np.zeros(6) if initial_pose is None else initial_pose, **kw)


def rigid_ok(T, near=None, tol: float = 1e-6, max_m: float = 1e4) -> bool:
    """A finite rigid transform (orthonormal, det +1, last row 0 0 0 1) within max_m of `near`."""
    T = np.asarray(T, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > tol or abs(np.linalg.det(R) - 1) > tol:
        return False
    if np.max(np.abs(T[3] - [0, 0, 0, 1])) > 0:
        return False
    ref = np.zeros(3) if near is None else np.asarray(near, float)
    return float(np.linalg.norm(T[:3, 3] - ref)) <= max_m


def estimate_ok(folder: Path, result) -> bool:
    """`result` an Estimate (or a list of them) whose poses are rigid and near the start, with a
    finite covariance."""
    ests = result if isinstance(result, list) else [result]
    for e in ests:
        if not rigid_ok(e.T_map_rover) or not np.all(np.isfinite(e.covariance)):
            return False
    return True


def _ticks(loc, n: int, t0: float = 0.0, **kw):
    out = []
    for i in range(n):
        out.append(
            loc.update(
                t0 + 0.05 * i,
                kw.get("data"),
                kw.get("imu", IMU_REST),
                kw.get("v", 0.0),
                kw.get("w", 0.0),
                odometry=kw.get("odometry_fn", lambda i: None)(i),
            )
        )
    return out


def _twins(make, warm: int, hostile, good):
    """Two localizers from `make()`, `warm` good ticks on both, `hostile(loc_a)` on the first;
    when it raises a LunarLocError, `good(loc)` on both must give the same estimate (state
    unchanged) and the error is re-raised; when it returns, that is the result."""
    from lunarloc.core.errors import LunarLocError

    a, b = make(), make()
    _ticks(a, warm)
    _ticks(b, warm)
    try:
        return hostile(a)
    except LunarLocError:
        ea, eb = good(a), good(b)
        if not (np.allclose(ea.T_map_rover, eb.T_map_rover, atol=1e-12) and a._tick == b._tick):
            raise StateChanged("the refused call changed the component's state") from None
        raise


def _update_case(
    name, hostile_args: dict, names: str, expect="error", warm=3, make=None, check=None
):
    """update() at t = 0.05 * warm with the IMU at rest, still, no images, except `hostile_args`."""

    def call(folder: Path):
        t = 0.05 * warm
        args = {
            "mission_time_s": t,
            "input_data": None,
            "imu": IMU_REST,
            "linear_speed": 0.0,
            "angular_speed": 0.0,
            **hostile_args,
        }

        def hostile(loc):
            return [loc.update(**args)] + _ticks(loc, 3, t + 0.05)

        return _twins(
            make or _loc, warm, hostile, lambda loc: loc.update(t, None, IMU_REST, 0.0, 0.0)
        )

    return Case(
        f"api/update-{name}", "api", None, expect, check or estimate_ok, call=call, names=names
    )


def _ctor_case(name, kwargs_fn, names: str, expect="error", check=None):
    def call(folder: Path):
        from lunarloc.online.component import OnlineLocalizer

        kw = {"reference": _ref(), "initial_pose": np.zeros(6), **kwargs_fn()}
        loc = OnlineLocalizer(**kw)
        return _ticks(loc, 5)

    return Case(
        f"api/init-{name}", "api", None, expect, check or estimate_ok, call=call, names=names
    )


def _call_case(name, fn, names: str, expect="error", check=None):
    return Case(
        f"api/{name}",
        "api",
        None,
        expect,
        check or (lambda folder, r: True),
        call=lambda folder: fn(),
        names=names,
    )


def _rot(axis: int, a: float) -> np.ndarray:
    from lunarloc.core.geometry import pose_to_matrix

    v = [0.0] * 6
    v[3 + axis] = a
    return pose_to_matrix(*v)


def _api_cases() -> list[Case]:
    C: list[Case] = []
    rng = np.random.default_rng(33)
    T_scale2 = np.diag([2.0, 2.0, 2.0, 1.0])
    T_reflect = np.diag([1.0, 1.0, -1.0, 1.0])
    T_random = rng.normal(size=(4, 4))
    T_ones = np.eye(4)
    T_ones[3] = 1.0
    T_singular = np.eye(4)
    T_singular[:3, 0] *= 1e-9
    T_skew = np.eye(4)
    T_skew[0, 1] = 1e-3  # 0.1 % off orthonormal: more than float32 round-off
    T_f32 = (_rot(2, 0.7) @ _rot(0, 0.01)).astype(np.float32)  # a float32 pose: valid
    T_far = np.eye(4)
    T_far[0, 3] = 1e300
    for name, pose in (
        ("pose-scale-2", T_scale2),
        ("pose-reflection", T_reflect),
        ("pose-random-4x4", T_random),
        ("pose-bottom-row-ones", T_ones),
        ("pose-near-singular", T_singular),
        ("pose-skewed-1e-3", T_skew),
        ("pose-translation-1e300", T_far),
        ("pose-6vec-1e300", np.array([1e300, 0, 0, 0, 0, 0])),
        ("pose-string", "identity"),
        ("pose-none", None),
        ("pose-3x3", np.eye(3)),
        ("pose-list-of-strings", [["a"] * 4] * 4),
        ("pose-bool-6vec", [True] * 6),
    ):
        C.append(_ctor_case(name, lambda pose=pose: {"initial_pose": pose}, "initial_pose"))
    C.append(_ctor_case("pose-float32-ok", lambda: {"initial_pose": T_f32}, "", "ok"))
    C.append(
        _ctor_case(
            "pose-6vec-ok", lambda: {"initial_pose": [1.0, 2.0, 0.1, 0.01, -0.02, 2.5]}, "", "ok"
        )
    )
    C.append(_ctor_case("lander-reflection", lambda: {"lander_pose": T_reflect}, "lander_pose"))
    C.append(
        _ctor_case(
            "lander-scale-1000",
            lambda: {"lander_pose": np.diag([1e3, 1e3, 1e3, 1.0])},
            "lander_pose",
        )
    )
    C.append(_ctor_case("config-string", lambda: {"config": "fast"}, "config"))
    C.append(_ctor_case("config-dict", lambda: {"config": {"max_keyframes": 100}}, "config"))
    C.append(
        _ctor_case(
            "detector-config-string", lambda: {"detector_config": "classical"}, "detector_config"
        )
    )
    C.append(_ctor_case("detector-config-int", lambda: {"detector_config": 7}, "detector_config"))
    C.append(_ctor_case("rig-string", lambda: {"rig": "ipex"}, "rig"))
    C.append(_ctor_case("reference-list", lambda: {"reference": H.rocks(10).tolist()}, "reference"))

    def rig_scaled():
        from lunarloc.online.component import CameraRig

        return CameraRig(T_rover_cam={"FrontLeft": T_scale2, "FrontRight": np.eye(4)})

    C.append(_call_case("rig-camera-pose-scale-2", rig_scaled, "FrontLeft"))

    def calib_str():
        from lunarloc.online.component import CameraRig

        return CameraRig.from_calibration("320", 180, fx=228.5)

    C.append(_call_case("rig-calibration-width-string", calib_str, "width"))

    def calib_huge():
        from lunarloc.online.component import CameraRig

        return CameraRig.from_calibration(10**9, 10**9, fx=1e9)

    C.append(_call_case("rig-calibration-width-1e9", calib_huge, "width"))

    def online_cfg(**kw):
        def f():
            from lunarloc.online.component import OnlineConfig

            return OnlineConfig(**kw)

        return f

    C.append(
        _call_case("config-max-keyframes-string", online_cfg(max_keyframes="many"), "max_keyframes")
    )
    C.append(
        _call_case("config-max-keyframes-1e12", online_cfg(max_keyframes=10**12), "max_keyframes")
    )
    C.append(
        _call_case(
            "config-travel-nan",
            online_cfg(keyframe_min_travel_m=float("nan")),
            "keyframe_min_travel_m",
        )
    )
    C.append(
        _call_case(
            "config-recent-attempts-negative",
            online_cfg(max_recent_attempts=-1),
            "max_recent_attempts",
        )
    )

    # update(): odometry, speeds, IMU, time, images
    for name, odo in (
        ("odometry-zeros", np.zeros((4, 4))),
        ("odometry-scale-1000", np.diag([1e3, 1e3, 1e3, 1.0])),
        ("odometry-reflection", T_reflect),
        ("odometry-random", T_random),
        ("odometry-nan-6vec", [np.nan] * 6),
        ("odometry-string", "odo"),
        ("odometry-translation-1e300", T_far),
    ):
        C.append(_update_case(name, {"odometry": odo}, "odometry"))
    for v in (1e300, -1e300, 5.0, float("inf")):
        C.append(_update_case(f"linear-speed-{v:g}", {"linear_speed": v}, "linear_speed"))
    C.append(_update_case("linear-speed-string", {"linear_speed": "fast"}, "linear_speed"))
    C.append(_update_case("linear-speed-none", {"linear_speed": None}, "linear_speed"))
    C.append(_update_case("linear-speed-bool", {"linear_speed": True}, "linear_speed"))
    for w in (1e300, 100.0):
        C.append(_update_case(f"angular-speed-{w:g}", {"angular_speed": w}, "angular_speed"))
    C.append(_update_case("imu-1e308", {"imu": [1e308] * 6}, "imu"))
    C.append(_update_case("imu-accel-1e4", {"imu": [1e4, 0, 1.622, 0, 0, 0]}, "imu"))
    C.append(_update_case("imu-gyro-1e3", {"imu": [0, 0, 1.622, 0, 0, 1e3]}, "imu"))
    C.append(_update_case("imu-nan", {"imu": [0, 0, np.nan, 0, 0, 0]}, "imu"))
    C.append(_update_case("imu-strings", {"imu": ["a"] * 6}, "imu"))
    C.append(_update_case("imu-dict", {"imu": {"ax": 0.0}}, "imu"))
    C.append(_update_case("imu-none", {"imu": None}, "imu"))
    C.append(_update_case("imu-5-values", {"imu": IMU_REST[:5]}, "imu"))
    C.append(
        _update_case("time-1e300-first-tick", {"mission_time_s": 1e300}, "mission_time_s", warm=0)
    )
    C.append(_update_case("time-1e300-after-ticks", {"mission_time_s": 1e300}, "mission_time_s"))
    C.append(_update_case("time-string", {"mission_time_s": "noon"}, "mission_time_s"))
    C.append(_update_case("time-none", {"mission_time_s": None}, "mission_time_s"))
    C.append(_update_case("time-bool", {"mission_time_s": True}, "mission_time_s"))
    C.append(_update_case("time-backwards", {"mission_time_s": 0.0}, "mission_time"))
    C.append(_update_case("time-jump", {"mission_time_s": 60.0}, "tick"))
    C.append(_update_case("time-nan", {"mission_time_s": float("nan")}, "mission_time_s"))
    img = np.zeros((90, 160), np.uint8)
    small = lambda: _loc(rig=_small_rig())
    for name, data in (
        ("images-ndarray-group", {"Grayscale": img}),
        (
            "images-ragged-list",
            {"Grayscale": {"FrontLeft": [[1, 2], [3]], "FrontRight": [[1, 2], [3]]}},
        ),
        ("images-string", {"Grayscale": {"FrontLeft": "img.png", "FrontRight": "img.png"}}),
        (
            "images-dict-image",
            {"Grayscale": {"FrontLeft": {"data": img}, "FrontRight": {"data": img}}},
        ),
        (
            "images-float-nan",
            {"Grayscale": {"FrontLeft": np.full((90, 160), np.nan), "FrontRight": img}},
        ),
        ("images-complex", {"Grayscale": {"FrontLeft": img.astype(complex), "FrontRight": img}}),
        ("images-object", {"Grayscale": {"FrontLeft": img.astype(object), "FrontRight": img}}),
        (
            "images-wrong-shape",
            {"Grayscale": {"FrontLeft": np.zeros((10, 10), np.uint8), "FrontRight": img}},
        ),
        ("images-list", [img, img]),
        (
            "images-rgb",
            {"Grayscale": {"FrontLeft": np.zeros((90, 160, 3), np.uint8), "FrontRight": img}},
        ),
    ):
        C.append(_update_case(name, {"input_data": data}, "input_data", make=small))
    C.append(
        _update_case(
            "images-ok",
            {"input_data": {"Grayscale": {"FrontLeft": img, "FrontRight": img}}},
            "",
            "ok",
            make=small,
        )
    )
    C.append(
        _update_case(
            "speeds-at-the-lac-limits-ok", {"linear_speed": 0.49, "angular_speed": -4.13}, "", "ok"
        )
    )
    C.append(_update_case("imu-bump-ok", {"imu": [3.0, -2.0, 1.622, 0.5, -0.5, 1.0]}, "", "ok"))

    def caller_odometry_ok():
        from lunarloc.core.geometry import pose_to_matrix

        loc = _loc()
        Ts = [pose_to_matrix(0.01 * i, 0.0, 0.0, 0.0, 0.0, 0.01 * i) for i in range(10)]
        ests = _ticks(loc, 10, odometry_fn=lambda i: Ts[i])
        return (
            ests if all(np.allclose(e.T_map_rover, T, atol=1e-9) for e, T in zip(ests, Ts)) else []
        )

    C.append(
        _call_case(
            "update-caller-odometry-ok",
            caller_odometry_ok,
            "",
            "ok",
            check=lambda f, r: bool(r) and estimate_ok(f, r),
        )
    )
    C.append(_call_case("reference-two-rocks", lambda: _loc_ref(H.rocks(2)), "reference"))

    def localize_strings():
        from lunarloc import localize

        return localize([["a", "b", "c"]] * 5, H.rocks(5))

    C.append(_call_case("localize-strings", localize_strings, "reference"))

    def localize_config_string():
        from lunarloc import LandmarkMap, localize

        return localize(LandmarkMap(H.rocks()), LandmarkMap(H.rocks()), "fast")

    C.append(_call_case("localize-config-string", localize_config_string, "config"))
    return C


def _loc_ref(xyz):
    from lunarloc.io.maps import LandmarkMap
    from lunarloc.online.component import OnlineLocalizer

    return OnlineLocalizer(LandmarkMap(xyz), np.zeros(6))


# ----------------------------------------------------------------------------- campaign specs


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return (
            "nan"
            if math.isnan(v)
            else ("inf" if v == math.inf else ("-inf" if v == -math.inf else repr(v)))
        )
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, range)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def spec_text(job: dict | None = None, grid: dict | None = None, name: str = "hostile") -> str:
    job = {"duration_s": 3.0, "reference_duration_s": 4.0, "width": 64, **(job or {})}
    grid = {"seed": [1], **(grid or {})}
    lines = ["[campaign]", f"name = {json.dumps(name)}", "[job]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in job.items()]
    lines += ["[grid]"] + [f"{k} = {_toml_value(v)}" for k, v in grid.items()]
    return "\n".join(lines) + "\n"


def _campaign_cases() -> list[Case]:
    C: list[Case] = []

    def camp(name, text, *extra, scheduler="sync"):
        def build(d: Path) -> list[str]:
            s = H.write(d, "spec.toml", text)
            sched = ["--scheduler", scheduler] if scheduler is not None else []
            return ["campaign", str(s), "-o", str(d / "out"), *sched, *extra]

        C.append(Case(f"campaign/{name}", "campaign", build))

    for k, v in (
        ("duration_s", 1e9),
        ("duration_s", math.inf),
        ("duration_s", math.nan),
        ("duration_s", 0.0),
        ("reference_duration_s", 1e9),
        ("image_rate_hz", 1e9),
        ("sun_elevation_deg", 1000.0),
        ("sun_elevation_deg", math.nan),
        ("sun_elevation_deg", -91.0),
        ("sun_azimuth_deg", 1e9),
        ("sun_azimuth_deg", math.inf),
        ("seed", True),
        ("seed", 1.5),
        ("seed", -1),
        ("seed", 2**64),
        ("n_rocks", True),
        ("n_rocks", -1),
        ("width", "640"),
        ("width", 10**6),
        ("width", True),
        ("min_reference_landmarks", -5),
        ("min_reference_landmarks", 10**9),
        ("plan", "foo"),
        ("odometry", "visual"),
        ("no_such_key", 1),
    ):
        camp(f"job-{k}-{v}", spec_text({k: v}) if k != "seed" else spec_text(grid={"seed": [v]}))
    camp(
        "grid-1e9-combinations",
        spec_text(
            grid={
                "seed": list(range(1000)),
                "n_rocks": list(range(3, 1003)),
                "sun_azimuth_deg": [float(a) for a in range(1000)],
            }
        ),
    )
    camp(
        "grid-1e6-combinations",
        spec_text(grid={"seed": list(range(1000)), "n_rocks": list(range(3, 1003))}),
    )
    camp("grid-10001-combinations", spec_text(grid={"seed": list(range(10001))}))
    camp(
        "grid-one-bad-value-deep",
        spec_text(grid={"seed": list(range(5000)), "sun_elevation_deg": [10.0, 1000.0]}),
    )
    camp("grid-axis-table", "[job]\nduration_s = 3.0\n[grid]\nseed = [{a = 1}]\n")
    camp("grid-axis-empty", "[grid]\nseed = []\n")
    camp("grid-duplicates", spec_text(grid={"seed": [1, 1]}))
    camp("grid-nested-list", spec_text(grid={"seed": [[1, 2]]}))
    camp("spec-deep-nesting", "a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    camp("spec-binary", np.random.default_rng(1).bytes(3000))
    camp("spec-utf16", spec_text().encode("utf-16"))
    camp("spec-empty", "")
    camp("spec-unknown-section", "[cluster]\nworkers = 3\n")
    camp("name-not-string", "[campaign]\nname = 5\n[grid]\nseed = [1]\n")
    for name, addr in (
        ("scheduler-malformed", "not a url::"),
        ("scheduler-bad-port", "tcp://127.0.0.1:notaport"),
        ("scheduler-unreachable", "tcp://127.0.0.1:1"),
        ("scheduler-unknown-protocol", "foo://bar:1"),
        ("scheduler-port-out-of-range", "tcp://127.0.0.1:70000"),
        ("scheduler-empty", ""),
    ):
        camp(name, spec_text(), scheduler=addr)

    def out_file(d: Path) -> list[str]:
        return [
            "campaign",
            str(H.write(d, "spec.toml", spec_text())),
            "-o",
            str(H.write(d, "out", "x")),
            "--scheduler",
            "sync",
        ]

    C.append(Case("campaign/out-is-a-file", "campaign", out_file))
    C.append(
        Case(
            "campaign/spec-is-a-folder",
            "campaign",
            lambda d: ["campaign", str(d), "-o", str(d / "out")],
        )
    )
    C.append(
        Case(
            "campaign/workers-0",
            "campaign",
            lambda d: [
                "campaign",
                str(H.write(d, "s.toml", spec_text())),
                "-o",
                str(d / "out"),
                "--workers",
                "0",
            ],
        )
    )
    return C


# ----------------------------------------------------------------------------- --config files


def _config_cases() -> list[Case]:
    C: list[Case] = []

    def runcfg(name, cfg_text: str | bytes, cmd="run", expect="error", check=None):
        def build(d: Path) -> list[str]:
            c = H.write(d, "c.json", cfg_text)
            if cmd == "run":
                a = H.write(d, "a.lac", H.lac_bytes(H.lac_members()))
                r = H.write(d, "b.csv", H.map_text())
                return [
                    "run",
                    str(a),
                    "--reference",
                    str(r),
                    "-o",
                    str(d / "run"),
                    "--no-plot",
                    "--config",
                    str(c),
                ]
            if cmd == "demo":
                return ["demo", "--out", str(d / "demo"), "--config", str(c)]
            if cmd == "localize":
                a = H.write(d, "a.csv", H.map_text())
                return ["localize", str(a), str(a), "--json", "--config", str(c)]
            (d / "data" / "csv").mkdir(parents=True)
            H.write(d, "data/csv/traverse_1.csv", H.traverse_text())
            H.write(d, "data/csv/traverse_2.csv", H.traverse_text(seed=2))
            return [
                "bench",
                "loop",
                "--data",
                str(d / "data"),
                "--out",
                str(d / "bo"),
                "--config",
                str(c),
            ]

        C.append(Case(f"config/{cmd}-{name}", "config", build, expect, check))

    def j(section, key, value):
        return json.dumps({section: {key: value}})

    for cmd in ("run", "bench-loop"):
        runcfg("epsilon-10", j("localization", "epsilon_m", 10.0), cmd)
        runcfg("epsilon-1e308", j("localization", "epsilon_m", 1e308), cmd)
        runcfg("window-1e300", j("loop", "window_m", 1e300), cmd)
    for key, v in (
        ("epsilon_z_m", 50.0),
        ("threads", 10**6),
        ("threads", 0),
        ("max_edges", -1),
        ("min_inliers", 10**12),
        ("yaw_step_deg", 1e-12),
        ("irls_rounds", 10**9),
        ("epsilon_m", "0.05"),
        ("epsilon_m", True),
        ("sigma_m", 1e300),
        ("refine_radius_m", 1e300),
        ("max_predicted_error_m", -1.0),
    ):
        runcfg(f"localization-{key}-{v}", j("localization", key, v))
    for key, v in (
        ("localize_every_m", 1e300),
        ("localize_every_s", 1e300),
        ("localize_every_m", 0.0),
        ("crop_margin_m", 1e300),
        ("min_window_landmarks", 10**12),
        ("keyframe_every_s", 1e-300),
    ):
        runcfg(f"loop-{key}-{v}", j("loop", key, v))
    runcfg("odometry-rate-1e9", j("odometry", "rate_hz", 1e9))
    runcfg("nan-literal", '{"localization": {"epsilon_m": NaN}}')
    runcfg("infinity-literal", '{"loop": {"window_m": Infinity}}')
    runcfg("deep-nesting", "[" * 100_000 + "]" * 100_000)
    runcfg("deep-nesting-object", '{"a":' * 50_000 + "1" + "}" * 50_000)
    runcfg("list", "[1, 2, 3]")
    runcfg("null", "null")
    runcfg("utf16", json.dumps({"loop": {}}).encode("utf-16"))
    runcfg("section-not-table", json.dumps({"loop": [1, 2]}))
    runcfg("unknown-section", json.dumps({"bogus": {}}))
    runcfg("huge-int", '{"localization": {"min_inliers": ' + "9" * 5000 + "}}")
    runcfg("epsilon-10", j("localization", "epsilon_m", 10.0), "localize")
    # valid files at the caps: still accepted
    runcfg(
        "epsilon-at-cap-ok",
        j("localization", "epsilon_m", 0.3),
        "localize",
        "ok",
        H.json_localized(None),
    )
    runcfg(
        "window-at-cap-ok",
        json.dumps(
            {"loop": {"window_m": 1e6, "localize_every_s": 1e7}, "localization": {"threads": 1}}
        ),
        "run",
        "ok",
        H.run_folder_ok("run"),
    )
    runcfg("scenario-duration-1e9", json.dumps({"scenario": {"duration_s": 1e9}}), "demo")
    runcfg("scenario-width-1e6", json.dumps({"scenario": {"width": 10**6}}), "demo")
    runcfg("scenario-sun-1000", json.dumps({"scenario": {"sun_elevation_deg": 1000.0}}), "demo")
    runcfg("scenario-not-table", json.dumps({"scenario": 5}), "demo")
    return C


# ----------------------------------------------------------------------------- score


def lac_grid(n: int = 20, seed: int = 0) -> np.ndarray:
    r = np.random.default_rng(seed)
    c = (np.arange(n) - (n - 1) / 2) * 0.15
    g = np.zeros((n, n, 4))
    g[:, :, 0], g[:, :, 1] = np.meshgrid(c, c, indexing="ij")
    g[:, :, 2] = r.normal(0, 0.1, (n, n))
    g[:, :, 3] = r.uniform(size=(n, n)) < 0.1
    return g


def _score_cases() -> list[Case]:
    C: list[Case] = []

    def score(name, tol=None, produced=None, truth=None, expect="error", check=None):
        def build(d: Path) -> list[str]:
            g = lac_grid()
            p = H.write(d, "p.npy", H.npy_bytes(g if produced is None else produced(g)))
            t = H.write(d, "t.npy", H.npy_bytes(g if truth is None else truth(g)))
            return [
                "score",
                str(p),
                str(t),
                "--json",
                *(["--height-tolerance", tol] if tol is not None else []),
            ]

        C.append(Case(f"score/{name}", "score", build, expect, check))

    for tol in ("-1", "nan", "inf", "-inf", "0", "1e9", "abc"):
        score(f"tolerance-{tol}", tol)

    def geometric(v):
        return lambda folder, so: json.loads(so.strip().splitlines()[-1])["geometric"] == v

    score("self-ok", expect="ok", check=geometric(1.0))
    score("tolerance-0.5-ok", "0.5", expect="ok", check=geometric(1.0))

    def nan_h(g):
        g = g.copy()
        g[3, 4, 2] = np.nan
        return g

    score("produced-nan-height", produced=nan_h)
    score("truth-nan-height", truth=nan_h)
    score("produced-inf-flag", produced=lambda g: np.where(np.arange(4) == 3, np.inf, g))
    score("shape-mismatch", produced=lambda g: g[:10, :10])
    score("object-npy", produced=lambda g: np.array([object()] * 4, dtype=object))
    score("2d-npy", produced=lambda g: g[:, :, 0])
    score("complex-npy", produced=lambda g: g.astype(complex))

    def trunc(d: Path) -> list[str]:
        b = H.npy_bytes(lac_grid())
        return [
            "score",
            str(H.write(d, "p.npy", b[: len(b) // 2])),
            str(H.write(d, "t.npy", b)),
            "--json",
        ]

    C.append(Case("score/truncated", "score", trunc))
    return C


# ----------------------------------------------------------------------------- damaged archives, odometry


def frames_with(cell: tuple[int, str, str], base: dict | None = None) -> dict[str, bytes]:
    """lac_members() with frames.csv's (row, column) set to a value."""
    m = dict(base or H.lac_members())
    lines = m["frames.csv"].decode().splitlines()
    cols = lines[0].split(",")
    row, col, value = cell
    cells = lines[1 + row].split(",")
    cells[cols.index(col)] = value
    lines[1 + row] = ",".join(cells)
    m["frames.csv"] = ("\n".join(lines) + "\n").encode()
    return m


def camera_with(cam: str, col: str, value: str, base: dict | None = None) -> dict[str, bytes]:
    m = dict(base or H.lac_members())
    name = f"cameras/{cam}/{cam}_frames.csv"
    lines = m[name].decode().splitlines()
    cols = lines[0].split(",")
    for i in range(1, len(lines)):
        cells = lines[i].split(",")
        cells[cols.index(col)] = value
        lines[i] = ",".join(cells)
    m[name] = ("\n".join(lines) + "\n").encode()
    return m


def _archive_cases() -> list[Case]:
    C: list[Case] = []

    def run(name, members_fn, *extra, expect="error", check=None):
        def build(d: Path) -> list[str]:
            a = H.write(d, "a.lac", H.lac_bytes(members_fn()))
            r = H.write(d, "b.csv", H.map_text())
            return ["run", str(a), "--reference", str(r), "-o", str(d / "run"), "--no-plot", *extra]

        C.append(Case(f"archive/run-{name}", "archive", build, expect, check))

    def odo(name, members_fn, *extra, expect="error", check=None):
        def build(d: Path) -> list[str]:
            a = H.write(d, "a.lac", H.lac_bytes(members_fn()))
            return ["odometry", str(a), "--json", str(d / "o.json"), *extra]

        C.append(Case(f"archive/odometry-{name}", "archive", build, expect, check))

    for col in ("x", "yaw"):
        for v in ("nan", "inf"):
            run(f"ground-truth-{col}-{v}", lambda col=col, v=v: frames_with((5, col, v)))
            odo(f"ground-truth-{col}-{v}", lambda col=col, v=v: frames_with((5, col, v)))
    run("ground-truth-x-1e300", lambda: frames_with((5, "x", "1e300")))
    # values at the bounds are data, not damage
    run(
        "speed-at-the-lac-limit-ok",
        lambda: frames_with((5, "linear_speed", "0.49")),
        "--odometry",
        "imu",
        expect="ok",
        check=H.run_folder_ok("run"),
    )
    run(
        "cameras-higher-ok",
        lambda: camera_with(
            "FrontRight", "camera_z", "0.9", camera_with("FrontLeft", "camera_z", "0.9")
        ),
        expect="ok",
        check=H.run_folder_ok("run"),
    )
    odo(
        "imu-bump-ok",
        lambda: frames_with((5, "accel_x", "30.0")),
        "--source",
        "imu",
        expect="ok",
        check=lambda d, so: (d / "o.json").is_file(),
    )
    odo("imu-accel-nan", lambda: frames_with((5, "accel_x", "nan")), "--source", "imu")
    odo("imu-gyro-inf", lambda: frames_with((5, "gyro_z", "inf")), "--source", "imu")
    run("imu-accel-nan", lambda: frames_with((5, "accel_x", "nan")), "--odometry", "imu")
    run("mission-time-nan", lambda: frames_with((5, "mission_time", "nan")))
    run(
        "linear-speed-1e300", lambda: frames_with((5, "linear_speed", "1e300")), "--odometry", "imu"
    )
    for col, v in (("camera_x", "nan"), ("camera_yaw", "inf"), ("camera_y", "1e300")):
        run(f"{col}-{v}", lambda col=col, v=v: camera_with("FrontLeft", col, v))
        odo(f"{col}-{v}", lambda col=col, v=v: camera_with("FrontLeft", col, v))
    run(
        "odometry-record-nan",
        lambda: H.with_member(
            "custom/odometry.csv",
            "frame,x,y,z,roll,pitch,yaw\n"
            + "".join(
                f"{f},{'nan' if f == 5 else 0.05 * f},0.0,0.0,0.0,0.0,0.0\n" for f in range(21)
            ),
        ),
        "--odometry",
        "record:odometry",
    )

    def share(name, members_fn):
        def build(d: Path) -> list[str]:
            a = H.write(d, "a.lac", H.lac_bytes(H.lac_members()))
            b = H.write(d, "b.lac", H.lac_bytes(members_fn()))
            return ["run", str(a), str(b), "--share-maps", "-o", str(d / "run"), "--no-plot"]

        C.append(Case(f"archive/share-maps-{name}", "archive", build))

    share("ground-truth-nan", lambda: frames_with((5, "x", "nan")))
    share("camera-x-nan", lambda: camera_with("FrontLeft", "camera_x", "nan"))

    # outputs of `odometry`
    def odo_out(name, prepare, *extra, expect="error", check=None):
        def build(d: Path) -> list[str]:
            a = H.write(d, "a.lac", H.lac_bytes(H.lac_members()))
            return ["odometry", str(a), *prepare(d), *extra]

        C.append(Case(f"output/odometry-{name}", "output", build, expect, check))

    odo_out("tum-existing", lambda d: ["-o", str(H.write(d, "o.tum", "old\n"))])
    odo_out("json-existing", lambda d: ["--json", str(H.write(d, "o.json", "{}"))])
    odo_out(
        "tum-existing-overwrite",
        lambda d: ["-o", str(H.write(d, "o.tum", "old\n"))],
        "--overwrite",
        expect="ok",
        check=lambda d, so: (d / "o.tum").read_text() != "old\n",
    )
    odo_out("tum-is-a-folder", lambda d: ["-o", str((d / "o.tum").mkdir() or d / "o.tum")])
    odo_out("tum-under-a-file", lambda d: ["-o", str(H.write(d, "f", "x") / "o.tum")])
    odo_out("json-under-a-file", lambda d: ["--json", str(H.write(d, "f", "x") / "o.json")])
    odo_out("source-foo", lambda d: ["--source", "foo"])

    def json_finite(folder: Path, so: str) -> bool:
        d = json.loads(
            (folder / "o.json").read_text(),
            parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)),
        )
        return isinstance(d, dict)

    odo_out("json-ok", lambda d: ["--json", str(d / "o.json")], expect="ok", check=json_finite)
    return C


def surface_cases() -> list[Case]:
    return _api_cases() + _campaign_cases() + _config_cases() + _score_cases() + _archive_cases()
