"""splat_train's modules import each other one way: no import circle.

Every import counts, at the top of a module or inside a function; ``from splat_train import x``
counts as an import of module ``x`` (a package ``__init__`` only hands names on and is left out).
The C++ kernels' loaders (``splat_train.cpu``) sit below everything that calls them.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "splat_train"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """{module: modules of the package it imports} for every module except package faces."""
    files = sorted((ROOT / PACKAGE).rglob("*.py"))
    modules = {_module_name(p) for p in files}
    graph: dict[str, set[str]] = {}
    for path in files:
        if path.name == "__init__.py":
            continue
        name = _module_name(path)
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            edges |= {t for t in targets if t in modules and t != name and not (ROOT / t.replace(".", "/")).is_dir()}
        graph[name] = edges
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_no_import_circle_in_splat_train():
    graph = import_graph()
    assert "splat_train.losses" in graph and "splat_train.cpu.ssim" in graph
    assert "splat_train.cpu.ssim" in graph["splat_train.losses"]  # the edge the test is about is seen
    cycle = _cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_cpu_kernels_import_no_caller():
    """The kernel loaders import only the torch building blocks they mirror, never the modules
    that call them (rasterize, losses, densify, trainer, ...)."""
    allowed = {"splat_train.projection", "splat_train._reference", "splat_train.sh", "splat_train.ssim_window"}
    for mod, deps in import_graph().items():
        if mod.startswith("splat_train.cpu."):
            outside = {d for d in deps if not d.startswith("splat_train.cpu.")} - allowed
            assert not outside, (mod, outside)
