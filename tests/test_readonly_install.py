"""`import lunarloc` and `lunarloc --help` work from a read-only install with an unwritable
$HOME: numba's cache=True kernels need a writable cache folder (issue 13)."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "lunarloc"


def _read_only_tree(root: Path) -> None:
    for p in sorted(root.rglob("*"), reverse=True) + [root]:
        mode = p.stat().st_mode
        p.chmod(
            mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)
            | stat.S_IROTH
            | (stat.S_IXOTH if p.is_dir() else 0)
        )


@pytest.fixture()
def readonly_install():
    base = Path(tempfile.mkdtemp(prefix="lunarloc-ro-"))
    base.chmod(0o755)
    pkg = base / "site" / "lunarloc"
    shutil.copytree(SRC, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    (base / "tmp").mkdir()
    (base / "tmp").chmod(0o1777)
    _read_only_tree(base / "site")
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PYTHONPATH")
    }
    env.update(
        PYTHONPATH=str(base / "site"), HOME=str(base / "site" / "home"), TMPDIR=str(base / "tmp")
    )
    yield base, env
    for p in [base, *base.rglob("*")]:
        if p.is_dir():
            p.chmod(0o755)
    shutil.rmtree(base, ignore_errors=True)


def _run(args, env):
    prefix = []
    if hasattr(os, "getuid") and os.getuid() == 0:
        # root ignores file modes: drop the capabilities that bypass them so the install
        # really is read-only (and $HOME unwritable) for the child
        if not shutil.which("setpriv"):
            pytest.skip(
                "running as root without setpriv: cannot make files read-only for the child"
            )
        prefix = ["setpriv", "--bounding-set=-dac_override,-dac_read_search,-fowner", "--"]
    proc = subprocess.run(
        [*prefix, sys.executable, *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd="/",
    )
    if prefix and proc.returncode != 0 and proc.stderr.startswith("setpriv:"):
        pytest.skip(f"cannot drop capabilities here: {proc.stderr.strip()}")
    return proc


def test_import_and_help_from_a_read_only_install(readonly_install):
    base, env = readonly_install
    code = (
        "import os, lunarloc; from lunarloc.association import clique; "
        "print(lunarloc.__file__); print(os.environ.get('NUMBA_CACHE_DIR'))"
    )
    proc = _run(["-c", code], env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    file_line, cache_line = proc.stdout.split("\n")[:2]
    assert file_line.startswith(str(base / "site")), "the read-only copy must be the one imported"
    assert cache_line.startswith(str(base / "tmp")), cache_line
    proc = _run(["-m", "lunarloc", "--help"], env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert "localize" in proc.stdout


def test_no_writable_place_warns(monkeypatch):
    from lunarloc.core import runtime as _runtime

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(_runtime, "_writable", lambda p: False)
    with pytest.warns(RuntimeWarning, match="NUMBA_CACHE_DIR"):
        assert _runtime.ensure_numba_cache_dir() is None
