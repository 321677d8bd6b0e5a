"""Issues 13 and 33: every hostile or broken input gives one clear error (exit 2, one line, no
traceback; for the API a LunarLocError naming the argument, state unchanged) or a correct
result. The corpus is generated (tests/_hostile.py: CSV, .npz, .lac, options, output paths;
tests/_hostile_surfaces.py: the OnlineLocalizer API, campaign specs, --config files, score,
odometry, damaged archives); each CLI case runs in-process through ``lunarloc.cli.app.main``.
Also: exit codes (130, 70, --debug), atomic outputs, and memory bounds measured with
tracemalloc."""

from __future__ import annotations

import errno
import gzip
import os
import tracemalloc
from pathlib import Path

import pytest

import _hostile as H
from lunarloc.cli.app import main

CASES = H.corpus(
    include_slow=False
)  # the few multi-second cases run in benchmarks/hostile_inputs.py


def test_corpus_is_large_and_covers_every_kind():
    kinds = {c.kind for c in CASES}
    assert len(CASES) >= 450
    assert kinds == {
        "csv",
        "npz",
        "lac",
        "option",
        "output",
        "api",
        "campaign",
        "config",
        "score",
        "archive",
    }
    assert all(sum(c.kind == k for c in CASES) >= 15 for k in kinds)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hostile_input(case, tmp_path):
    o = H.run_case(case, tmp_path / "case", timeout_s=120)  # a hang fails the case, not the suite
    want = {
        "error": ("clear error",),
        "ok": ("correct result",),
        "either": ("clear error", "correct result"),
    }
    assert o.outcome in want[case.expect], f"{case.name}: {o.outcome} (exit {o.rc}): {o.message}"
    if o.outcome == "clear error":
        assert "Traceback" not in o.message
    leftovers = [p.name for p in (tmp_path / "case").rglob(".*.tmp-*")]
    assert not leftovers, f"temporary files left behind: {leftovers}"


# ----------------------------------------------------------------------------- exit codes


def _traverse(tmp_path: Path) -> Path:
    return H.write(tmp_path, "t.csv", H.traverse_text())


def test_ctrl_c_exits_130_and_leaves_no_output(tmp_path, monkeypatch, capsys):
    import lunarloc.io.maps as maps

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(maps, "traverse_map", interrupted)
    out = tmp_path / "m.csv"
    assert main(["map", str(_traverse(tmp_path)), "-o", str(out)]) == 130
    assert not out.exists()
    assert "interrupted" in capsys.readouterr().err


def test_interrupted_write_leaves_neither_partial_file_nor_temporary(tmp_path):
    from lunarloc.io.outputs import atomic_open

    target = tmp_path / "d.csv"
    target.write_text("previous\n")
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(target, "w") as fh:
            fh.write("frame,x\n1,2\n")
            raise KeyboardInterrupt
    assert target.read_text() == "previous\n"  # untouched
    assert [p.name for p in tmp_path.iterdir()] == ["d.csv"]


def test_detect_interrupted_mid_archive_writes_nothing(tmp_path, monkeypatch):
    import lunarloc.perception.detector as det

    real = det.detect_archive

    def two_then_interrupt(*a, **k):
        for i, fd in enumerate(real(*a, **k)):
            if i == 1:
                raise KeyboardInterrupt
            yield fd

    monkeypatch.setattr(det, "detect_archive", two_then_interrupt)
    lac = H.write(tmp_path, "a.lac", H.lac_bytes(H.lac_members()))
    out = tmp_path / "det.csv"
    assert main(["detect", str(lac), "-o", str(out)]) == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.lac"]


def test_eof_error_is_not_an_interruption(tmp_path, monkeypatch, capsys):
    import lunarloc.io.maps as maps

    def eof(*a, **k):
        raise EOFError("ran out of input")

    monkeypatch.setattr(maps, "traverse_map", eof)
    assert main(["map", str(_traverse(tmp_path)), "-o", str(tmp_path / "m.csv")]) == 70
    err = capsys.readouterr().err
    assert "internal error: EOFError" in err and "aborted" not in err


def test_empty_npz_is_an_input_error(tmp_path, capsys):
    empty = H.write(tmp_path, "e.npz", b"")
    assert main(["localize", str(empty), str(empty)]) == 2
    assert "e.npz: empty file" in capsys.readouterr().err


def test_unexpected_exception_is_one_line_and_debug_shows_traceback(tmp_path, monkeypatch, capsys):
    import lunarloc.io.maps as maps

    def boom(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(maps, "traverse_map", boom)
    args = ["map", str(_traverse(tmp_path)), "-o", str(tmp_path / "m.csv")]
    assert main(args) == 70
    err = capsys.readouterr().err
    assert (
        err.strip() == "internal error: RuntimeError: boom (rerun with --debug for the traceback)"
    )
    assert main(["--debug", *args]) == 70
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and err.strip().endswith(
        "(rerun with --debug for the traceback)"
    )


def test_debug_shows_the_traceback_of_input_errors_too(tmp_path, capsys):
    missing = str(tmp_path / "nope.csv")
    assert main(["localize", missing, missing]) == 2
    assert "Traceback" not in capsys.readouterr().err
    assert main(["--debug", "localize", missing, missing]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "nope.csv: no such file" in err


def test_full_disk_is_a_clear_error(tmp_path, monkeypatch, capsys):
    real_replace = os.replace

    def full(src, dst):
        if str(dst).endswith("m.csv"):
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", full)
    assert main(["map", str(_traverse(tmp_path)), "-o", str(tmp_path / "m.csv")]) == 2
    assert "m.csv: no space left on device" in capsys.readouterr().err
    assert not list(tmp_path.glob(".*tmp-*"))


def test_demo_check_failure_exits_1(monkeypatch, tmp_path):
    import lunarloc.cli.commands_run as cr
    import lunarloc.pipeline.scenario as scenario

    fake = {
        "fixes": 0,
        "ate_odometry": {"rmse_m": 1.0, "max_m": 1.0},
        "ate_corrected": {"rmse_m": 1.0, "max_m": 1.0},
        "ate_online": {"rmse_m": 1.0, "max_m": 1.0},
    }
    monkeypatch.setattr(scenario, "run_scenario", lambda *a, **k: fake)
    monkeypatch.setattr(cr, "_print_summary", lambda *a, **k: None)
    assert main(["demo", "--out", str(tmp_path / "d")]) == 1


# ----------------------------------------------------------------------------- memory bounds


def _peak_mib(fn) -> float:
    tracemalloc.start()
    try:
        fn()
    except Exception:  # noqa: BLE001 - refusal is what most of these expect
        pass
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 1024**2


def test_npz_bomb_and_huge_shape_are_refused_without_allocating(tmp_path, monkeypatch):
    import zipfile

    from lunarloc.io import inputs
    from lunarloc.io.maps import load_map

    monkeypatch.setattr(
        inputs, "MAX_NPZ_MEMBER_BYTES", 32 * 1024**2
    )  # the mechanism, at a test-sized limit
    bomb = tmp_path / "bomb.npz"
    n = 48 * 1024**2 // 24
    with (
        zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf,
        zf.open("positions_xyz.npy", "w", force_zip64=True) as fh,
    ):
        fh.write(H.npy_header((n, 3)))
        chunk = b"\0" * (8 * 1024**2)
        for _ in range(n * 24 // len(chunk)):
            fh.write(chunk)
    assert bomb.stat().st_size < 2 * 1024**2
    assert _peak_mib(lambda: load_map(bomb)) < 8
    shape = H.write(
        tmp_path,
        "shape.npz",
        H.npz_bytes({"positions_xyz.npy": H.npy_header((10**12, 3)) + b"\0" * 64}),
    )
    assert _peak_mib(lambda: load_map(shape)) < 8


def test_lac_member_of_newlines_is_refused_with_bounded_memory(tmp_path, monkeypatch):
    import lunarloc.io.lac.archive as lac

    monkeypatch.setattr(
        lac, "MAX_TABLE_BYTES", 16 * 1024**2
    )  # the mechanism, at a test-sized limit
    LacArchive = lac.LacArchive
    m = H.lac_members()
    m["frames.csv"] += b"\n" * (lac.MAX_TABLE_BYTES + 1)
    p = H.write(tmp_path, "a.lac", gzip.compress(H.tar_bytes(m), 1))
    del m
    assert p.stat().st_size < 1024**2
    assert _peak_mib(lambda: LacArchive(p)) < 8
    with pytest.raises(Exception, match="over the .*limit"):
        LacArchive(p)


def test_blank_lines_cost_nothing_in_an_archive_table(tmp_path):
    from lunarloc.io.lac.archive import LacArchive

    m = H.lac_members()
    m["frames.csv"] += b"\n" * 1024**2
    p = H.write(tmp_path, "a.lac", H.lac_bytes(m))
    # the 1 MiB member read a few times over, never a list of 1 M empty rows (~64 MiB)
    assert _peak_mib(lambda: LacArchive(p).close()) < 8


def test_traverse_csv_memory_is_proportional_to_its_content(tmp_path):
    from lunarloc.io.maps import load_traverse

    text = H.traverse_text(n_frames=1200, rock_xyz=H.rocks(200))
    p = H.write(tmp_path, "t.csv", text)
    size_mib = p.stat().st_size / 1024**2
    peak = _peak_mib(lambda: load_traverse(p))
    assert size_mib > 2
    assert peak < size_mib + 4, (
        f"{peak:.1f} MiB for a {size_mib:.1f} MiB file"
    )  # Python lists: ~3.5x


def test_library_writer_never_replaces_a_device_or_folder(tmp_path):
    from lunarloc.core.errors import OutputError
    from lunarloc.io.maps import LandmarkMap, save_map

    lm = LandmarkMap(H.rocks(5))
    with pytest.raises(OutputError, match="not a regular file"):
        save_map(
            lm, (tmp_path / "m.csv").mkdir() or tmp_path / "m.csv"
        )  # a folder named like a map
    if os.path.exists("/dev/null"):
        from lunarloc.io.outputs import atomic_open

        with pytest.raises(OutputError, match="not a regular file"):
            with atomic_open("/dev/null") as fh:
                fh.write("x")
        assert not Path("/dev/null").is_file()
