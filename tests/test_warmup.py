"""warm_up compiles the association kernels once per process; the command runs it."""

from lunarloc.cli.app import main
from lunarloc.localization.warmup import warm_up


def test_warm_up_once_per_process(capsys):
    assert main(["warm-up", "--no-aot"]) == 0
    assert "association kernels ready" in capsys.readouterr().out
    assert warm_up() == 0.0  # already done in this process: nothing left to compile
    assert warm_up(force=True) > 0.0


def test_warm_up_reaches_every_search_kernel():
    # in a fresh process: after warm_up, the kernels a large localization uses (the
    # per-bin bounds included) are compiled or loaded, so no later call compiles
    import subprocess
    import sys

    code = (
        "from lunarloc.localization.warmup import warm_up; warm_up(jit=True)\n"
        "from lunarloc.association import clique, graph\n"
        "missing = [f.__name__ for f in (clique._bin_bounds, clique._peeled_max_clique, clique._peeled_graph,\n"
        "           graph._yaw_chunk_incidences, graph._bucket_pairs, graph._graph_3d) if not f.signatures]\n"
        "assert not missing, missing\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=600)
