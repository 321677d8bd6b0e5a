"""Ahead-of-time kernels (lunarloc.association.aot): used when built from the current sources,
numba's JIT otherwise, with the same answers either way."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from lunarloc.association import aot


def _python(code: str, **env) -> subprocess.CompletedProcess:
    full = {k: v for k, v in os.environ.items() if k != "LUNARLOC_AOT"}
    full.update(env)
    proc = subprocess.run(
        [sys.executable, "-c", code], env=full, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def _built() -> bool:
    return (aot._HERE / f"{aot.AOT_MODULE}.json").exists() and aot.aot_status().startswith("loaded")


def test_import_lunarloc_does_not_import_numba():
    # the kernels are compiled or loaded at their first call, not at import
    out = _python(
        "import sys, lunarloc, lunarloc.localization.localize, lunarloc.association.graph\n"
        "print('numba' in sys.modules)"
    ).stdout.split()
    assert out == ["False"]


def test_argument_checks_are_exact():
    checks = aot._compile_checks(
        [["array", "<i4", 1], ["scalar", "i8"], ["scalar", "f8"], ["scalar", "b1"]]
    )
    a = np.arange(6, dtype=np.int32)
    assert aot._matches(checks, (a, 3, 0.5, True))
    assert aot._matches(checks, (a, np.int64(3), np.float64(0.5), np.bool_(False)))
    assert not aot._matches(checks, (a.astype(np.int64), 3, 0.5, True))  # dtype
    assert not aot._matches(checks, (a[::2], 3, 0.5, True))  # not contiguous
    assert not aot._matches(checks, (a.reshape(2, 3), 3, 0.5, True))  # ndim
    ro = a.copy()
    ro.setflags(write=False)
    assert not aot._matches(checks, (ro, 3, 0.5, True))  # read-only: another numba type
    assert not aot._matches(checks, (a, True, 0.5, True))  # bool is not int64 to numba
    assert not aot._matches(checks, (a, 3, 1, True))  # int is not float64
    assert not aot._matches(checks, (a, 3, 0.5))  # count
    assert not aot._matches(checks, (list(a), 3, 0.5, True))
    assert aot._compile_checks([["scalar", "c16"]]) is None  # unknown: stays on the JIT path


def test_missing_stale_or_broken_build_is_not_loaded(tmp_path, monkeypatch):
    monkeypatch.delenv("LUNARLOC_AOT", raising=False)
    assert aot._load_table(tmp_path) == {}
    assert aot._STATE["reason"].startswith("not built")
    meta = {"format": aot.AOT_FORMAT, "module": "_aot_kernels.so", "sources": {}, "kernels": {}}
    (tmp_path / f"{aot.AOT_MODULE}.json").write_text(json.dumps(meta))
    assert aot._load_table(tmp_path) == {}
    assert aot._STATE["reason"].startswith("stale"), aot._STATE["reason"]
    meta["sources"] = aot._sources()  # current sources, but no module file
    (tmp_path / f"{aot.AOT_MODULE}.json").write_text(json.dumps(meta))
    assert aot._load_table(tmp_path) == {}
    assert aot._STATE["reason"].startswith("cannot load"), aot._STATE["reason"]
    (tmp_path / "_aot_kernels.so").write_bytes(b"not an ELF file")
    assert aot._load_table(tmp_path) == {}
    assert aot._STATE["reason"].startswith("cannot load"), aot._STATE["reason"]
    (tmp_path / f"{aot.AOT_MODULE}.json").write_text("{")
    assert aot._load_table(tmp_path) == {}
    assert aot._STATE["reason"].startswith("unreadable")
    monkeypatch.setenv("LUNARLOC_AOT", "0")
    assert aot._load_table(tmp_path) == {}
    assert aot._STATE["reason"].startswith("disabled")


_PAIR = """
import sys, json, numpy as np
from lunarloc.core.geometry import euler_to_rotation, make_transform, transform_points
from lunarloc.localization.config import LocalizationConfig, Mode
from lunarloc.localization.localize import localize
from lunarloc.io.maps import LandmarkMap
from lunarloc.association import aot
rng = np.random.default_rng(3)
ref_xyz = np.c_[rng.uniform(-10, 10, (120, 2)), rng.normal(0, 0.2, 120)]
T = make_transform(euler_to_rotation(0.0, 0.0, 1.1), np.array([4.0, -1.0, 0.2]))
veh_xyz = transform_points(np.linalg.inv(T), ref_xyz[:45]) + rng.normal(0, 0.005, (45, 3))
out = []
for mode in Mode:
    r = localize(LandmarkMap(ref_xyz, frame="ref"), LandmarkMap(veh_xyz, frame="veh"), LocalizationConfig(mode=mode))
    out.append([bool(r.success), int(r.num_inliers), np.asarray(r.inliers).tolist(), np.round(r.T_ref_veh, 9).tolist()])
print(json.dumps({"numba": "numba" in sys.modules, "status": aot.aot_status(), "results": out}))
"""


def test_jit_fallback_gives_the_answer_when_disabled():
    res = json.loads(_python(_PAIR, LUNARLOC_AOT="0").stdout)
    assert res["status"].startswith("disabled")
    assert res["numba"]  # the JIT path ran
    assert all(r[0] and r[1] >= 40 for r in res["results"]), res["results"]


@pytest.mark.skipif(
    not _built(), reason="ahead-of-time kernels not built here (`lunarloc warm-up` builds them)"
)
def test_built_kernels_skip_numba_and_agree_with_the_jit():
    aot_res = json.loads(_python(_PAIR).stdout)
    jit_res = json.loads(_python(_PAIR, LUNARLOC_AOT="0").stdout)
    assert aot_res["status"].startswith("loaded"), aot_res["status"]
    assert not aot_res["numba"], "a localization with the built kernels must not import numba"
    assert jit_res["numba"]
    assert aot_res["results"] == jit_res["results"]


@pytest.mark.skipif(
    not _built(), reason="ahead-of-time kernels not built here (`lunarloc warm-up` builds them)"
)
def test_a_signature_not_built_falls_back_to_the_jit():
    code = (
        "import sys, numpy as np\n"
        "from lunarloc.association import graph\n"
        "rng = np.random.default_rng(0)\n"
        "dh, phi, dz = rng.uniform(0, 3, 16), rng.uniform(-3, 3, 16), rng.normal(0, 1, 16)\n"
        "a = graph._bucket_pairs(4, dh, phi, dz, 1.0, 4, 1.0, 7)\n"  # float64 arrays: built
        "print('numba' in sys.modules)\n"
        "f4 = [x.astype(np.float32) for x in (dh, phi, dz)]\n"
        "b = graph._bucket_pairs(4, *f4, 1.0, 4, 1.0, 7)\n"  # float32: not built -> JIT
        "print('numba' in sys.modules, b[2].dtype, all(np.array_equal(x, y) for x, y in zip(a[:2], b[:2])))\n"
    )
    lines = _python(code).stdout.splitlines()
    assert lines == ["False", "True float64 True"]


@pytest.mark.skipif(
    not _built(), reason="ahead-of-time kernels not built here (`lunarloc warm-up` builds them)"
)
def test_a_module_from_another_build_is_not_loaded(tmp_path):
    import shutil

    meta = json.loads((aot._HERE / f"{aot.AOT_MODULE}.json").read_text())
    shutil.copyfile(aot._HERE / meta["module"], tmp_path / meta["module"])
    (tmp_path / f"{aot.AOT_MODULE}.json").write_text(json.dumps(meta))
    code = (
        "import sys; from pathlib import Path; from lunarloc.association import aot, clique, graph\n"
        f"folder = Path({str(tmp_path)!r})\n"
        "t = aot._load_table(folder); print(len(t) > 0, aot._STATE['reason'])\n"
    )
    assert _python(code).stdout.startswith("True loaded")  # the copy as built: loads
    meta["build_id"] += 1  # the table of another build
    (tmp_path / f"{aot.AOT_MODULE}.json").write_text(json.dumps(meta))
    out = _python(code).stdout
    assert out.startswith("False cannot load") and "build id" in out, out


def test_warm_up_reports_a_failed_build_and_still_succeeds(monkeypatch, capsys):
    from lunarloc.cli.app import main

    def no_compiler(*a, **k):
        raise OSError("gcc: command not found")

    monkeypatch.setattr(aot, "build_aot", no_compiler)
    assert main(["warm-up"]) == 0
    out = capsys.readouterr()
    assert "association kernels ready" in out.out
    assert "ahead-of-time kernels not built (OSError: gcc: command not found)" in out.err
    assert "numba's cache is used instead" in out.err
