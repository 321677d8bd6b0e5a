"""The package's structure in figures: modules, import cycles, long lines, and the longest and
most complex functions (cyclomatic complexity by radon, the ``dev`` extra).

    python benchmarks/structure.py [--src src] [--top 10]

Every import counts in the cycle search, function-level ones included, as in
tests/test_layers.py (which enforces the layer order); docs/architecture.md quotes the output.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path


def module_imports(pkg: Path) -> dict[str, set[str]]:
    """Each module of `pkg` and the package modules it imports (anywhere in its body)."""
    graph: dict[str, set[str]] = {}
    for path in pkg.rglob("*.py"):
        parts = path.relative_to(pkg.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(pkg.name):
                deps |= {f"{node.module}.{a.name}" for a in node.names} | {node.module}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith(pkg.name)}
        graph[name] = deps
    return {
        m: {d for d in deps if d in graph and d != m and not d.startswith(m + ".")}
        for m, deps in graph.items()
        if m != pkg.name
    }


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Groups of modules that import one another in a cycle (strongly connected, > 1 module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))
    for v in graph:
        if v not in index:
            visit(v)
    return groups


def functions(pkg: Path) -> list[tuple[int, int, str]]:
    """(lines, cyclomatic complexity, name) of every function and method."""
    try:
        from radon.complexity import cc_visit
    except ImportError:
        raise SystemExit("radon is needed: pip install 'lunarloc[dev]' (or pip install radon)")
    rows = []
    for path in sorted(pkg.rglob("*.py")):
        rel = path.relative_to(pkg).as_posix()
        for b in cc_visit(path.read_text()):  # methods come on their own, with their class
            if type(b).__name__ == "Class":
                continue
            owner = f"{b.classname}." if getattr(b, "classname", None) else ""
            rows.append((b.endline - b.lineno + 1, b.complexity, f"{rel}:{owner}{b.name}"))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", type=Path, default=Path(__file__).resolve().parents[1] / "src")
    ap.add_argument("--top", type=int, default=10)
    args = ap.parse_args()
    pkg = args.src / "lunarloc"
    files = sorted(pkg.rglob("*.py"))
    lines = [line for f in files for line in f.read_text().splitlines()]
    top = [p for p in pkg.iterdir() if p.suffix == ".py" and p.stem not in ("__init__", "__main__")]
    cycles = import_cycles(module_imports(pkg))
    print(f"source lines: {len(lines)} in {len(files)} files; top-level modules: {len(top)}")
    print(f"import cycles (function-level imports counted): {len(cycles)}")
    for group in cycles:
        print("   " + " <-> ".join(group))
    print(f"lines over 100 characters: {sum(len(line) > 100 for line in lines)}")
    rows = functions(pkg)
    print(f"{args.top} longest functions (lines, CC):")
    for n, cc, name in sorted(rows, reverse=True)[: args.top]:
        print(f"   {n:4d} {cc:3d}  {name}")
    print(f"{args.top} most complex functions (CC, lines):")
    for n, cc, name in sorted(rows, key=lambda r: (-r[1], -r[0]))[: args.top]:
        print(f"   {cc:3d} {n:4d}  {name}")


if __name__ == "__main__":
    main()
