"""warm_up compiles the association kernels once per process; the command runs it."""

from lunarloc.cli.app import main
from lunarloc.warmup import warm_up


def test_warm_up_once_per_process(capsys):
    assert main(["warm-up"]) == 0
    assert "association kernels ready" in capsys.readouterr().out
    assert warm_up() == 0.0  # already done in this process: nothing left to compile
    assert warm_up(force=True) > 0.0
