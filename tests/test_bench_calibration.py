"""benchmarks/calibration.py writes its JSON only where asked (``--json PATH`` or ``--out PATH``),
never a calibration.json into the working directory by default."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import calibration as bench


def test_no_file_by_default_and_the_json_where_asked(tmp_path, monkeypatch, capsys):
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    args = ["--per-family", "0"]  # no case: the table and the file alone
    bench.main(args)
    assert list(work.iterdir()) == []
    assert "confident-wrong: 0 of 0 runs" in capsys.readouterr().out
    for flag in ("--json", "--out"):
        out = tmp_path / f"calib{flag}.json"
        bench.main([*args, flag, str(out)])
        got = json.loads(out.read_text())
        assert got == {"rows": [], "outcomes": []}
    assert list(work.iterdir()) == []
