"""CI's real-data gate must be able to fail: `.ci/realdata-gate` on data whose paper pairs
cannot localize exits 1 (a check failed), and on a folder with no traverses exits 2."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
GATE = ROOT / ".ci" / "realdata-gate"


def _write_unrelated_traverse(path: Path, rng: np.random.Generator) -> None:
    """A traverse CSV in the LunarLoc layout whose rocks share nothing with any other file:
    40 rocks of an independent random field, each seen from 8 frames with 5 mm noise."""
    rocks = np.c_[rng.uniform(-10, 10, (40, 2)), rng.normal(0, 0.2, 40)]
    lines = ["frame,x,y,z,detections,boulders"]
    for f in range(1, 81):
        seen = rocks[(f - 1) % 10 :: 10] if f > 0 else rocks
        pts = seen + rng.normal(0, 0.005, seen.shape)
        body = ", ".join(f"({x:.4f}, {y:.4f}, {z:.4f})" for x, y, z in pts)
        lines.append(f'{f},{0.05 * f:.3f},0.0,0.0,{len(pts)},"[{body}]"')
    path.write_text("\n".join(lines) + "\n")


def _gate(data: Path, out: Path) -> subprocess.CompletedProcess:
    if not (ROOT / ".venv" / "bin" / "lunarloc").exists():
        pytest.skip("the gate runs the project's .venv (make venv)")
    return subprocess.run(
        ["bash", str(GATE), str(data), str(out), "--paper"],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_gate_fails_on_data_that_cannot_localize(tmp_path):
    rng = np.random.default_rng(5)
    csv_dir = tmp_path / "data" / "csv"
    csv_dir.mkdir(parents=True)
    for k in (3, 5, 7, 12):
        _write_unrelated_traverse(csv_dir / f"traverse_{k}.csv", rng)
    proc = _gate(tmp_path / "data", tmp_path / "out")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "CHECK FAILED" in proc.stdout


def test_gate_exits_2_on_a_folder_without_traverses(tmp_path):
    (tmp_path / "empty").mkdir()
    proc = _gate(tmp_path / "empty", tmp_path / "out")
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
