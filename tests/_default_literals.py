"""Where the numbers that the project's defaults define appear as literals (the AST walk of
tests/test_defaults_once.py).

A *default* is a number bound to a name in a defining file (:data:`SOURCES`: the config
dataclasses, the registries, the defaults modules): a module-level ``NAME = 3``, a dataclass
field ``name: int = 3``, an entry ``"name": 3`` of a module-level dict (a recipe), an element of
a module-level tuple. Every other file of the package code, the CLIs and the workflow is walked
(Python by its AST; the workflow's ``.smk`` files by their tokens, the numbers of their shell
strings' ``--flag N`` included), and a literal is a *repeat* of a default when

* it is bound to the default's name (a keyword ``name=3``, a parameter default, an assignment,
  a dict key, an argparse flag ``--name`` with ``default=3``, a rule's ``name=3``, a shell
  ``--name 3``) and has its value, the value not :data:`TRIVIAL`; or
* it has a :func:`distinctive` value of a default, bound to any name or none.

Two defining files that bind one value to one name define one default twice: a repeat too.

Numbers compare by absolute value (``-1`` is ``1``). A file's own module- or class-level
definitions are its one place for their values (another concept that happens to share a
number: floaters' TAU_REL and the Bridge's ALPHA_MIN, both 0.05), unless a definition binds a
default's value to the default's name: that restates the default, a repeat, or, where a stage
may not import the defining one, an entry of ``shared`` with the reason.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from dataclasses import dataclass
from pathlib import Path

#: the files that define defaults (relative to the repository root)
SOURCES = (
    "splat_train/config.py", "splat_train/recipes.py", "splat_train/testpose.py", "splat_train/strategy/mcmc.py",
    "splat_train/strategy/configs.py", "splat_train/parts/configs.py", "splat_train/fields.py",
    "bridge/core.py", "bridge/equations.py", "bridge/selection.py",
    "vggt_init/defaults.py", "vggt_init/run.py",
    "evaluation/metrics/pose.py", "evaluation/metrics/floaters.py",
    "evaluation/initialisers/random_init.py", "evaluation/initialisers/oracle.py",
    "evaluation/initialisers/posed.py", "evaluation/initialisers/colmap_baseline.py",
    "evaluation/initialisers/ba_init.py",
    "camio/ply.py", "camio/prepare.py", "runtime/view_defaults.py",
)
#: the packages whose code is walked, and the workflow
PACKAGES = ("camio", "vggt_init", "bridge", "splat_train", "evaluation")
#: numbers too common to name one default: never repeats by value, nor by name
TRIVIAL = frozenset({0, 1, 2, 0.5, 10, 100, 1000})
# floats too common to stand for one default by value alone (a name ties them, see module doc)
_COMMON_FLOATS = frozenset({0.2, 0.25, 0.3, 0.4, 0.75, 0.02, 1.5, 2.5})


def distinctive(value: float) -> bool:
    """A number that names one default wherever it appears: not trivial, not a small or round
    integer (<= 16, a power of two, a multiple of ten), not a float of one significant digit 1
    (0.1, 0.01, 1e-6) nor a common fraction."""
    if value in TRIVIAL:
        return False
    if float(value).is_integer():
        i = int(value)
        return not (i <= 16 or i & (i - 1) == 0 or i % 10 == 0)
    mantissa = f"{value:.6e}".split("e")[0].rstrip("0").rstrip(".")
    return mantissa != "1" and value not in _COMMON_FLOATS


@dataclass(frozen=True)
class Literal:
    """A number written in a file: where, its absolute value, the name it is bound to (normalised
    by :func:`norm`; None when it is not bound to one)."""

    path: str
    line: int
    value: float
    name: str | None = None


def norm(name: str) -> str:
    """``--max-points``, ``MAX_POINTS``, ``max_points`` -> ``max_points``; a leading
    ``default_`` is dropped (``DEFAULT_STEPS`` is ``steps``)."""
    name = name.lstrip("-").replace("-", "_").lower()
    return name[len("default_"):] if name.startswith("default_") else name


def _num(node: ast.AST) -> float | None:
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        return _num(node.operand)
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        return abs(node.value)
    return None


def _target(node: ast.AST) -> str | None:
    if isinstance(node, ast.Attribute):
        return node.attr
    return getattr(node, "id", None)


def _bound(name: str, value: ast.AST, path: str) -> list[Literal]:
    """The numbers of ``value`` bound to ``name``: itself, the elements of a tuple or list, the
    entries of a dict (bound to their keys)."""
    if isinstance(value, ast.Dict):
        return [lit for k, v in zip(value.keys, value.values)
                if isinstance(k, ast.Constant) and isinstance(k.value, str) for lit in _bound(k.value, v, path)]
    if isinstance(value, (ast.Tuple, ast.List)):
        return [lit for e in value.elts for lit in _bound(name, e, path)]
    v = _num(value)
    return [] if v is None else [Literal(path, value.lineno, v, norm(name))]


def definitions(text: str, path: str) -> list[Literal]:
    """The numbers a Python file binds to names at module level and in class bodies."""
    out: list[Literal] = []
    for st in ast.parse(text).body:
        body = st.body if isinstance(st, ast.ClassDef) else [st]
        for s in body:
            if isinstance(s, ast.Assign) and len(s.targets) == 1 and _target(s.targets[0]):
                out += _bound(_target(s.targets[0]), s.value, path)
            elif isinstance(s, ast.AnnAssign) and s.value is not None and _target(s.target):
                out += _bound(_target(s.target), s.value, path)
    return out


def _python_literals(text: str, path: str) -> list[Literal]:
    tree = ast.parse(text)
    names: dict[int, str] = {}  # id(number node) -> the name it is bound to

    def bind(name: str | None, value: ast.AST | None) -> None:
        while isinstance(value, ast.UnaryOp):
            value = value.operand
        if name and value is not None and _num(value) is not None:
            names[id(value)] = norm(name)

    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and id(node.value) not in names:  # add_argument's default: its flag
            bind(node.arg, node.value)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            a = node.args
            pos = a.posonlyargs + a.args
            for arg, d in zip(pos[len(pos) - len(a.defaults):], a.defaults):
                bind(arg.arg, d)
            for arg, d in zip(a.kwonlyargs, a.kw_defaults):
                bind(arg.arg, d)
        elif isinstance(node, ast.Assign):
            for t in node.targets:
                bind(_target(t), node.value)
        elif isinstance(node, ast.AnnAssign):
            bind(_target(node.target), node.value)
        elif isinstance(node, ast.Dict):
            for k, v in zip(node.keys, node.values):
                if isinstance(k, ast.Constant) and isinstance(k.value, str):
                    bind(k.value, v)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
            flags = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
            dest = [k.value.value for k in node.keywords if k.arg == "dest" and isinstance(k.value, ast.Constant)]
            for kw in node.keywords:
                if kw.arg == "default":
                    bind((dest or [f for f in flags if f.startswith("--")] or flags or [None])[0], kw.value)
    return [Literal(path, node.lineno, _num(node), names.get(id(node))) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and _num(node) is not None]


_SHELL_FLAG = re.compile(r"(--[A-Za-z][\w-]*)\s+(-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\b")


def _workflow_literals(text: str, path: str) -> list[Literal]:
    """The numbers of a Snakemake file: its number tokens (a ``name=N`` or ``name: N`` binds
    N to name) and the ``--flag N`` of its strings."""
    out = []
    toks = [t for t in tokenize.generate_tokens(io.StringIO(text).readline)
            if t.type not in (tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.COMMENT)]
    for i, t in enumerate(toks):
        if t.type == tokenize.NUMBER:
            j = i - 1 - (i >= 1 and toks[i - 1].string in "-+")
            name = toks[j - 1].string if j >= 1 and toks[j].string in ("=", ":") and toks[j - 1].type == tokenize.NAME \
                else None
            out.append(Literal(path, t.start[0], abs(ast.literal_eval(t.string)), norm(name) if name else None))
        elif t.type == tokenize.STRING:
            for m in _SHELL_FLAG.finditer(t.string):
                line = t.start[0] + t.string[:m.start()].count("\n")
                out.append(Literal(path, line, abs(float(m.group(2))), norm(m.group(1))))
    return out


def literals(path: Path, root: Path) -> list[Literal]:
    """Every number written in ``path`` (Python or a Snakemake file), with the name it is bound to."""
    rel = str(path.relative_to(root))
    text = path.read_text()
    return _python_literals(text, rel) if path.suffix == ".py" else _workflow_literals(text, rel)


def walked_files(root: Path) -> list[Path]:
    """The package code (CLIs included) and the workflow (rules, Snakefiles, scripts)."""
    files = [p for pkg in PACKAGES for p in sorted((root / pkg).rglob("*.py"))]
    files += sorted((root / "workflow").rglob("*.py")) + sorted((root / "workflow").rglob("*.smk"))
    return files + [p for p in (root / "Snakefile", root / "workflow" / "Snakefile") if p.is_file()]


def repeats(root: Path, sources=SOURCES, shared: dict | None = None) -> list[str]:
    """One line per repeat (module docstring): ``path:line: N (name) is the default of
    home:name``. ``shared``: {(path, name): reason} of definitions that restate a default on
    purpose (a stage that may not import the defining one)."""
    shared = shared or {}
    defaults: dict[float, dict[str, str]] = {}  # value -> {name: home}
    out = []
    for rel in sources:
        for d in definitions((root / rel).read_text(), rel):
            if d.value in TRIVIAL:
                continue
            home = defaults.setdefault(d.value, {}).setdefault(d.name, rel)
            if home != rel and (rel, d.name) not in shared:  # two defining files, one default
                out.append(f"{rel}:{d.line}: {d.value:g} ({d.name}) is the default of {home}:{d.name}")
    homes = {v: set(names.values()) for v, names in defaults.items()}
    for path in walked_files(root):
        rel = str(path.relative_to(root))
        own = {d.value for d in definitions(path.read_text(), rel)} if path.suffix == ".py" else set()
        for lit in literals(path, root):
            names = defaults.get(lit.value)
            if not names or rel in homes[lit.value] or (rel, lit.name) in shared:
                continue
            if lit.name in names:
                out.append(f"{rel}:{lit.line}: {lit.value:g} ({lit.name}) is the default of "
                           f"{names[lit.name]}:{lit.name}")
            elif distinctive(lit.value) and lit.value not in own:
                name, home = sorted(names.items())[0]
                out.append(f"{rel}:{lit.line}: {lit.value:g} is the default of {home}:{name}")
    return sorted(set(out))
