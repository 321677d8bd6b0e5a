"""The package's layers: imports flow only downward, and no module imports itself in a cycle.

Every import counts, function-level ones included (they may keep heavy libraries out of
``import lunarloc``, never hide an upward dependency). See docs/architecture.md."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "src" / "lunarloc"
LAYERS = [
    "core",
    "io",
    "association",
    "perception",
    "odometry",
    "mapping",
    "localization",
    "fusion",
    "online",
    "config",
    "sim",
    "viz",
    "pipeline",
    "cli",
]  # lowest first; a layer imports its own or lower ones


def _module_imports() -> dict[str, set[str]]:
    graph = {}
    for path in PKG.rglob("*.py"):
        parts = path.relative_to(PKG.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.ImportFrom)
                and node.module
                and node.module.startswith("lunarloc")
            ):
                deps |= {f"{node.module}.{a.name}" for a in node.names} | {node.module}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith("lunarloc")}
        graph[name] = deps
    return {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}


def _layer(module: str) -> int:
    return LAYERS.index(module.split(".")[1])


def test_every_subpackage_has_a_layer():
    top = {
        p.stem if p.is_file() else p.name
        for p in PKG.iterdir()
        if p.suffix == ".py" or (p / "__init__.py").exists()
    }
    assert top - {"__init__", "__main__"} <= set(LAYERS)


def test_imports_only_flow_downward():
    upward = [
        f"{m} -> {d}"
        for m, deps in _module_imports().items()
        if m != "lunarloc" and not m.endswith("__main__")
        for d in deps
        if d != "lunarloc" and _layer(d) > _layer(m)
    ]
    assert not upward, "\n".join(sorted(upward))


def test_no_import_cycles():
    graph = {m: deps for m, deps in _module_imports().items() if m != "lunarloc"}
    state, cycles = {}, []

    def visit(m, stack):
        state[m] = "open"
        for d in sorted(graph.get(m, ())):
            if d.startswith(m + "."):
                continue  # a package's __init__ importing its own submodule is not a cycle
            if state.get(d) == "open":
                cycles.append(" -> ".join(stack[stack.index(d) :] + [d]))
            elif d not in state:
                visit(d, stack + [d])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "\n".join(cycles)
