"""Import layers: no import circle anywhere in the project's packages.

Every import counts, at the top of a module or inside a function (a function-level import that
only hides a circle from the interpreter is still a circle). ``from pkg import x`` counts as an
import of module ``pkg.x`` when that is a module, else of ``pkg``; relative imports are resolved.
A package ``__init__`` only hands names on and is left out of the module graph.

Three levels are checked:

* packages: the graph between the top-level packages has no cycle. The ground floor
  (:data:`GROUND_FLOOR`: runtime, camio, imgmetrics, one job each) imports no stage, each of its
  packages only those below it; a stage (:data:`STAGES`) imports the ground floor and no other
  stage (what several stages use lives on the ground floor; stages talk through files);
* subpackages: inside a package, its subpackages (e.g. evaluation.metrics, splat_train.render.cpu) and
  top-level modules import each other one way; evaluation's subpackages follow its layers
  (:data:`EVALUATION_LAYERS`);
* modules: inside each package, subpackages included, the modules import each other one way;
* the tool rooms (:data:`TOOL_ROOMS`: benchmarks, experiments) are not shipped and run from the
  clone: they may import every package, no package imports them, and their subpackages and
  modules import each other one way across both rooms, benchmarks above experiments (the GPU
  check and the backend comparisons reuse the studies' command runner, GPU table and the
  sparse-view grid's command; the studies import nothing of the benchmarks).

The C++ kernels' loaders (``splat_train.render.cpu``) sit below everything that calls them, and
``splat_train.render`` below the rest of splat_train (:data:`RENDER_LAYERS`).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The ground floor, lowest first, each package importing only those before it:
# runtime (what every command shares while it runs: flags, logging, memory, C++ builds),
# camio (cameras, scenes, file formats), imgmetrics (image-quality metrics).
GROUND_FLOOR = ("runtime", "camio", "imgmetrics")
STAGES = ("vggt_init", "bridge", "splat_train", "evaluation")
PACKAGES = GROUND_FLOOR + STAGES
# Not shipped (pyproject's package list leaves them out); run from the clone as python -m ...:
# benchmarks (time and memory), experiments (quality studies and the results page).
TOOL_ROOMS = ("benchmarks", "experiments")
# evaluation's subpackages by job, lowest first: each imports only those before it
# (evaluation/__init__.py); evaluation.__main__, the CLI, sits above them all.
EVALUATION_LAYERS = ("evaluation.metrics", "evaluation.initialisers", "evaluation.reports", "evaluation.study")


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(node: ast.AST, name: str, is_init: bool) -> list[str]:
    """Dotted names an import statement may refer to (module, and module.attr for each name)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    if node.level:
        base = name.split(".") if is_init else name.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        module = ".".join(base + ([node.module] if node.module else []))
    else:
        module = node.module or ""
    return [module] + [f"{module}.{a.name}" for a in node.names]


def import_graph(root: Path = ROOT, packages=PACKAGES) -> dict[str, set[str]]:
    """{module: project modules it imports}, every import statement of every module counted.

    An import of a package face (``import camio``) is an edge to the package name itself, so
    that the package graph sees it; within a package, such edges are dropped.
    """
    files = sorted(p for pkg in packages for p in (root / pkg).rglob("*.py"))
    modules = {_module_name(p, root) for p in files}
    graph: dict[str, set[str]] = {}
    for path in files:
        name = _module_name(path, root)
        is_init = path.name == "__init__.py"
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            for target in _imported(node, name, is_init):
                if target in modules and target != name:
                    edges.add(target)
        graph[name] = edges
    return graph


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """{package: other packages its modules import}."""
    out: dict[str, set[str]] = {}
    for mod, deps in graph.items():
        top = mod.split(".")[0]
        out.setdefault(top, set()).update(d.split(".")[0] for d in deps if d.split(".")[0] != top)
    return out


def module_graph(graph: dict[str, set[str]], package: str, root: Path = ROOT) -> dict[str, set[str]]:
    """The edges between modules of one package, package faces (``__init__``) left out."""
    faces = {m for m in graph if (root / m.replace(".", "/")).is_dir()}
    return {m: {d for d in deps if d.split(".")[0] == package and d not in faces}
            for m, deps in graph.items() if m.split(".")[0] == package and m not in faces}


def _unit(module: str) -> str:
    """The part of its package a module belongs to: its subpackage (``evaluation.metrics`` for
    ``evaluation.metrics.pose``), else the module itself (``evaluation.__main__``)."""
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else module


def subpackage_graph(graph: dict[str, set[str]], package: str) -> dict[str, set[str]]:
    """{subpackage or top-level module of ``package``: the others of them it imports}."""
    out: dict[str, set[str]] = {}
    for mod, deps in graph.items():
        if mod.split(".")[0] != package or mod == package:
            continue
        unit = _unit(mod)
        out.setdefault(unit, set()).update(
            _unit(d) for d in deps if d.split(".")[0] == package and d != package and _unit(d) != unit)
    return out


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as [a, b, ..., a], or None."""
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


def test_graph_sees_imports_inside_functions():
    graph = import_graph()
    assert "splat_train.render.cpu.ssim" in graph["splat_train.losses"]
    assert "camio.datasets" in graph["camio.scene"]  # imported inside functions only


def test_no_cycle_between_packages():
    cycle = find_cycle(package_graph(import_graph()))
    assert cycle is None, " -> ".join(cycle)


def test_package_layers():
    """The ground floor imports no stage, each of its packages only those below it; a stage
    imports the ground floor and no other stage."""
    pkgs = package_graph(import_graph())
    for i, pkg in enumerate(GROUND_FLOOR):
        assert pkgs.get(pkg, set()) <= set(GROUND_FLOOR[:i]), (pkg, pkgs[pkg])
    for stage in STAGES:
        assert pkgs[stage] <= set(GROUND_FLOOR), (stage, pkgs[stage])


def test_every_package_has_its_floor():
    """The packages ``pip install`` ships are the ones these rules cover, and each top-level
    folder with an ``__init__.py`` besides tests, scripts and the tool rooms is one of them."""
    import re

    include = re.search(r"^include = \[(.*)\]$", (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    shipped = {s.strip().strip('"').rstrip("*") for s in include.split(",")}
    assert shipped == set(PACKAGES), shipped ^ set(PACKAGES)
    folders = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests", "scripts", *TOOL_ROOMS}
    assert folders == set(PACKAGES), folders ^ set(PACKAGES)


def test_graph_sees_subpackages():
    graph = import_graph()
    assert "evaluation.metrics.pose" in graph["evaluation.initialisers.posed"]
    assert "evaluation.reports.results" in graph["evaluation.study.collect"]
    subs = subpackage_graph(graph, "evaluation")
    assert set(EVALUATION_LAYERS) <= set(subs), sorted(subs)
    assert {p.name for p in (ROOT / "evaluation").iterdir() if (p / "__init__.py").is_file()} == {
        s.split(".")[1] for s in EVALUATION_LAYERS}, "a new evaluation subpackage needs its place in EVALUATION_LAYERS"


def test_no_circle_between_subpackages():
    graph = import_graph()
    cycles = {p: find_cycle(subpackage_graph(graph, p)) for p in PACKAGES}
    found = [f"{p}: " + " -> ".join(c) for p, c in cycles.items() if c]
    assert not found, "; ".join(found)


def test_evaluation_layers():
    """metrics < initialisers < reports < study: a subpackage imports only those below it, and
    none imports the CLI (evaluation.__main__)."""
    subs = subpackage_graph(import_graph(), "evaluation")
    for i, layer in enumerate(EVALUATION_LAYERS):
        above = set(subs[layer]) - set(EVALUATION_LAYERS[:i])
        assert not above, f"{layer} imports {sorted(above)}, which are not below it"


def test_no_import_circle_inside_a_package():
    graph = import_graph()
    cycles = {p: find_cycle(module_graph(graph, p)) for p in PACKAGES}
    found = [f"{p}: " + " -> ".join(c) for p, c in cycles.items() if c]
    assert not found, "; ".join(found)


def test_checker_finds_function_level_circle(tmp_path):
    """The checker itself: a circle hidden by an import inside a function, and a package cycle."""
    (tmp_path / "pa").mkdir()
    (tmp_path / "pb").mkdir()
    (tmp_path / "pa" / "__init__.py").write_text("")
    (tmp_path / "pb" / "__init__.py").write_text("")
    (tmp_path / "pa" / "x.py").write_text("from pa.y import f\n")
    (tmp_path / "pa" / "y.py").write_text("def f():\n    from . import x\n    from pb import z\n")
    (tmp_path / "pb" / "z.py").write_text("import pa.x\n")
    graph = import_graph(tmp_path, ("pa", "pb"))
    assert find_cycle(module_graph(graph, "pa", tmp_path)) in (["pa.x", "pa.y", "pa.x"], ["pa.y", "pa.x", "pa.y"])
    assert find_cycle(package_graph(graph)) is not None


def test_checker_finds_circle_between_subpackages(tmp_path):
    """Two subpackages that import each other through different modules: no module circle,
    a subpackage circle (one of them inside a function)."""
    for d in ("pa", "pa/s1", "pa/s2"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "__init__.py").write_text("")
    (tmp_path / "pa" / "s1" / "a.py").write_text("from pa.s2 import b\n")
    (tmp_path / "pa" / "s1" / "d.py").write_text("")
    (tmp_path / "pa" / "s2" / "b.py").write_text("")
    (tmp_path / "pa" / "s2" / "c.py").write_text("def f():\n    from pa.s1.d import g\n")
    graph = import_graph(tmp_path, ("pa",))
    assert find_cycle(module_graph(graph, "pa", tmp_path)) is None
    assert find_cycle(subpackage_graph(graph, "pa")) in (["pa.s1", "pa.s2", "pa.s1"], ["pa.s2", "pa.s1", "pa.s2"])


def test_cpu_kernels_import_no_caller():
    """The kernel loaders import only the torch building blocks they mirror, never the modules
    that call them (rasterize, losses, densify, trainer, ...)."""
    allowed = {"splat_train.render.projection", "splat_train.render._reference", "splat_train.render.sh"}
    for mod, deps in import_graph().items():
        if mod.startswith("splat_train.render.cpu."):
            outside = {d for d in deps if d.startswith("splat_train.")
                       and not d.startswith("splat_train.render.cpu")} - allowed
            assert not outside, (mod, outside)


# splat_train.render's layers, lowest first (splat_train/render/__init__.py): the torch maths,
# the fast paths built on it, the front. A module imports only modules of its own layer or below.
RENDER_LAYERS = (
    ("splat_train.render.projection", "splat_train.render.sh", "splat_train.render._reference"),
    ("splat_train.render.cpu", "splat_train.render._tiles", "splat_train.render._gsplat_backend"),
    ("splat_train.render.rasterize",),
)


def _render_layer(module: str) -> int:
    return next(i for i, layer in enumerate(RENDER_LAYERS)
                for unit in layer if module == unit or module.startswith(unit + "."))


def test_render_is_splat_trains_floor():
    """Nothing in splat_train.render imports the rest of splat_train, and inside it each module
    imports only its own layer or those below (maths < kernels and backends < the front)."""
    graph = import_graph()
    render = {m: deps for m, deps in graph.items() if m.startswith("splat_train.render.")}
    assert "splat_train.render.cpu.raster" in render and "splat_train.render.rasterize" in render
    faces = {"splat_train.render", "splat_train.render.cpu"}
    for mod, deps in render.items():
        if mod in faces:
            continue
        outside = {d for d in deps if d.startswith("splat_train") and d not in faces
                   and not d.startswith("splat_train.render.")}
        assert not outside, f"{mod} imports {sorted(outside)} from above splat_train.render"
        above = {d for d in deps if d.startswith("splat_train.render.") and d not in faces
                 and _render_layer(d) > _render_layer(mod)}
        assert not above, f"{mod} imports {sorted(above)}, which are above its layer"


def test_training_sits_above_what_it_is_made_of():
    """splat_train.training (the run loop and its files) is imported only by the CLI and the
    viewer, never by the config, views, losses, parameters, strategies, parts or rasterizer."""
    graph = import_graph()
    users = {m for m, deps in graph.items()
             if not m.startswith("splat_train.training") and any(d.startswith("splat_train.training") for d in deps)}
    assert users <= {"splat_train.__main__", "splat_train.view.source"}, sorted(users)
    assert "splat_train.training.snapshot" in graph["splat_train.view.source"]


def _tool_units(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """{subpackage or top-level module of a tool room: the others of both rooms it imports}
    (the rooms' package faces left out)."""
    out: dict[str, set[str]] = {}
    for mod, deps in graph.items():
        if mod.split(".")[0] not in TOOL_ROOMS or mod in TOOL_ROOMS:
            continue
        unit = _unit(mod)
        out.setdefault(unit, set()).update(
            _unit(d) for d in deps if d.split(".")[0] in TOOL_ROOMS and d not in TOOL_ROOMS and _unit(d) != unit)
    return out


def test_no_package_imports_a_tool_room():
    """A shipped package never imports benchmarks or experiments: an installed copy has neither."""
    graph = import_graph(packages=PACKAGES + TOOL_ROOMS)
    found = sorted(f"{m} -> {d}" for m, deps in graph.items() if m.split(".")[0] in PACKAGES
                   for d in deps if d.split(".")[0] in TOOL_ROOMS)
    assert not found, found


def test_no_circle_in_the_tool_rooms():
    """The tool rooms import one way: benchmarks (timing the stages, and the studies' runner for
    the backend comparisons) above experiments, which imports nothing of benchmarks; no circle
    between their subpackages and modules (experiments.sparse_views, benchmarks.gpu_check, ...)."""
    graph = import_graph(packages=PACKAGES + TOOL_ROOMS)
    up = sorted(f"{mod} -> {d}" for mod, deps in graph.items() if mod.split(".")[0] == "experiments"
                for d in deps if d.split(".")[0] == "benchmarks")
    assert not up, up
    units = _tool_units(graph)
    assert "experiments._proc" in units["experiments.sparse_views"]  # the checker sees across the rooms
    assert "experiments.sparse_views" in units["benchmarks.backend_agree"]
    cycle = find_cycle(units)
    assert cycle is None, " -> ".join(cycle)
    for room in TOOL_ROOMS:
        cycle = find_cycle(module_graph(graph, room))
        assert cycle is None, " -> ".join(cycle)
