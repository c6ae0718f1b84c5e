"""Where the numbers that the project's defaults define appear as literals (the AST walk of
tests/test_defaults_once.py).

A *default* is a number bound to a name in a defining file (:data:`SOURCES`: the config
dataclasses, the registries, the defaults modules): a module-level ``NAME = 3``, a dataclass
field ``name: int = 3``, a parameter ``name=3`` of a settings class's ``__init__``, an entry
``"name": 3`` of a module-level dict (a recipe), an element of a module-level tuple. Every
other file of the package code, the CLIs, the scripts, the workflow and its YAML is walked
(Python by its AST; the workflow's ``.smk`` files by their tokens, the numbers of their shell
strings' ``--flag N`` included; YAML below), and a literal is a *repeat* of a default when

* it is bound to the default's name (a keyword ``name=3``, a parameter default, an assignment,
  a dict key, an argparse flag ``--name`` with ``default=3``, a rule's ``name=3``, a shell
  ``--name 3``, a YAML ``name: 3``) and has its value, the value not 0 or 1
  (:data:`TRIVIAL_BY_NAME`: seeds, switches, counts that mean "none" or "one"); or
* it has a :func:`distinctive` value of a default, bound to any name or none.

Two defining files that bind one value to one name define one default twice: a repeat too.

Round numbers (0.5, 10, 100, 500, 1000, ...) are repeats by name only: ``conf_scale: 10.0`` in
a YAML file restates the oracle's default, ``width=10`` does not.

YAML is walked too (:data:`YAML_FILES`: config.yaml, config/*.yaml, the workflow schema and
profiles): a number under a key is bound to that key and is a repeat by that name only (a
config's value is the user's choice; the study's noise level 0.05 is not the Bridge's
ALPHA_MIN); in the schema a property's ``default:`` is bound to the property, its range
keywords (``minimum``, ``maxItems``, ...) are not defaults and are skipped
(tests/test_config_ranges.py compares them with the flags'). Strings hold
numbers too, in help texts and descriptions: a number after the word *default* is bound to the
flag (``help="... (default 518)"``) or the property it describes, any other distinctive number
in them counts by value. A number quoted right after the constant that holds it
(``DEFAULT_STEPS, 500``: the schema's descriptions name the code's constant and its value, and
a test compares the two) is left alone.

Numbers compare by absolute value (``-1`` is ``1``). A file's own module- or class-level
definitions are its one place for their values (another concept that happens to share a
number: floaters' TAU_REL and the Bridge's ALPHA_MIN, both 0.05), unless a definition binds a
default's value to the default's name: that restates the default, a repeat, or, where a stage
may not import the defining one, an entry of ``shared`` with the reason.

:func:`hand_written_defaults` is the stricter rule for help texts: a number after the word
*default* in an argparse help is written by hand whatever its value (0 and 1 included), where
``%(default)s`` or the formatted constant would follow the default.
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
    "splat_train/config.py", "splat_train/tree.py", "splat_train/recipes.py", "splat_train/testpose.py", "splat_train/strategy/mcmc.py",
    "splat_train/strategy/configs.py", "splat_train/parts/configs.py", "splat_train/fields.py",
    "bridge/core.py", "bridge/equations.py", "bridge/selection.py",
    "vggt_init/defaults.py", "vggt_init/run.py",
    "evaluation/metrics/pose.py", "evaluation/metrics/floaters.py", "evaluation/metrics/align.py",
    "evaluation/reports/thumbs.py",
    "evaluation/initialisers/random_init.py", "evaluation/initialisers/oracle.py",
    "evaluation/initialisers/posed.py", "evaluation/initialisers/colmap_baseline.py",
    "evaluation/initialisers/ba_init.py", "evaluation/initialisers/colmap_run.py",
    "camio/ply.py", "camio/prepare.py", "camio/synthetic.py", "runtime/view_defaults.py",
)
#: the packages whose code is walked (CLIs included), the command-line scripts, and the workflow
PACKAGES = ("camio", "vggt_init", "bridge", "splat_train", "evaluation", "runtime", "imgmetrics", "scripts")
#: the YAML files walked: the configs, the workflow schema and profiles (globs from the root)
YAML_FILES = ("config.yaml", "config/*.yaml", "workflow/schemas/*.yaml", "workflow/profiles/**/*.yaml")
#: numbers too common to name one default by value alone (a name ties them: module doc)
TRIVIAL = frozenset({0, 1, 2, 0.5, 10, 100, 1000})
#: numbers too common to name one default even by name: seeds, switches, "none" and "one"
TRIVIAL_BY_NAME = frozenset({0, 1})
#: schema keywords whose numbers are ranges or sizes of a value, not its default
SCHEMA_RANGES = frozenset({"minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "minItems", "maxItems",
                           "minProperties", "maxProperties", "minLength", "maxLength", "multipleOf"})
# floats too common to stand for one default by value alone (a name ties them, see module doc)
_COMMON_FLOATS = frozenset({0.2, 0.25, 0.3, 0.4, 0.75, 0.02, 1.5, 2.5})
# integers with common other meanings (24: three doubles in bytes, a binary record's size)
_COMMON_INTS = frozenset({24})


def distinctive(value: float) -> bool:
    """A number that names one default wherever it appears: not trivial, not a small or round
    integer (<= 16, a power of two, a multiple of ten, 24), not a float of one significant digit 1
    (0.1, 0.01, 1e-6) nor a common fraction."""
    if value in TRIVIAL:
        return False
    if float(value).is_integer():
        i = int(value)
        return not (i <= 16 or i & (i - 1) == 0 or i % 10 == 0 or i in _COMMON_INTS)
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
    by_value: bool = True  # False: a YAML value, a repeat by its name only (module doc)


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


def _init_defaults(cls: ast.ClassDef, path: str) -> list[Literal]:
    """The numeric parameter defaults of a class's ``__init__`` (a settings class written by
    hand, like a dataclass's fields)."""
    out = []
    for fn in cls.body:
        if isinstance(fn, ast.FunctionDef) and fn.name == "__init__":
            a = fn.args
            pos = a.posonlyargs + a.args
            pairs = list(zip(pos[len(pos) - len(a.defaults):], a.defaults)) + list(zip(a.kwonlyargs, a.kw_defaults))
            out += [lit for arg, d in pairs if d is not None for lit in _bound(arg.arg, d, path)]
    return out


def definitions(text: str, path: str) -> list[Literal]:
    """The numbers a Python file binds to names at module level, in class bodies and in the
    parameters of a class's ``__init__``."""
    out: list[Literal] = []
    for st in ast.parse(text).body:
        body = st.body if isinstance(st, ast.ClassDef) else [st]
        if isinstance(st, ast.ClassDef):
            out += _init_defaults(st, path)
        for s in body:
            if isinstance(s, ast.Assign) and len(s.targets) == 1 and _target(s.targets[0]):
                out += _bound(_target(s.targets[0]), s.value, path)
            elif isinstance(s, ast.AnnAssign) and s.value is not None and _target(s.target):
                out += _bound(_target(s.target), s.value, path)
    return out


_TEXT_NUMBER = re.compile(r"(?<![\w.,/-])(\d{1,3}(?:,\d{3})+|\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)(?![\w,]\d|[\w/])")
_AFTER_DEFAULT = re.compile(r"default(?:s| value)?\s*[:=]?\s*(?:is\s+)?$", re.I)
_AFTER_CONSTANT = re.compile(r"\b[A-Z][A-Z0-9_]+,\s*$")


def text_numbers(text: str, name: str | None, path: str, line: int) -> list[Literal]:
    """The numbers of a help text or description starting at ``line``: one after the word
    *default* is bound to ``name`` (the flag or the property the text describes), one right
    after the constant that holds it (``DEFAULT_STEPS, 500``) is left out, any other is unbound."""
    out = []
    for m in _TEXT_NUMBER.finditer(text):
        before = text[max(0, m.start() - 40):m.start()]
        if _AFTER_CONSTANT.search(before):
            continue
        value = abs(float(m.group(1).replace(",", "")))
        bound = norm(name) if name and _AFTER_DEFAULT.search(before) else None
        out.append(Literal(path, line + text[:m.start()].count("\n"), value, bound))
    return out


def _string_of(node: ast.AST) -> str | None:
    """The text of a string or f-string (its literal parts; a formatted value reads the code)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)
    return None


def _help_literals(tree: ast.AST, path: str) -> list[Literal]:
    """The numbers of argparse help texts (``help=`` of add_argument, ``description=`` and
    ``epilog=`` of a parser), bound to the flag where they follow the word *default*."""
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        flags = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
        dest = [k.value.value for k in node.keywords if k.arg == "dest" and isinstance(k.value, ast.Constant)]
        name = (dest or [f for f in flags if f.startswith("--")] or flags or [None])[0]
        for kw in node.keywords:
            text = _string_of(kw.value) if kw.arg in ("help", "description", "epilog") else None
            if text is not None:
                out += text_numbers(text, name if kw.arg == "help" else None, path, kw.value.lineno)
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
            if isinstance(node, ast.Constant) and _num(node) is not None] + _help_literals(tree, path)


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


def _yaml_literals(text: str, path: str) -> list[Literal]:
    """The numbers of a YAML file (module doc): under a key, bound to it; a schema property's
    ``default`` bound to the property; range keywords skipped; strings read by :func:`text_numbers`
    (``description:`` bound to its property)."""
    import yaml

    out: list[Literal] = []

    def walk(node, name: str | None, prop: str | None) -> None:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                key = k.value if isinstance(k, yaml.ScalarNode) else None
                if key in SCHEMA_RANGES:
                    continue
                if key in ("default", "description"):
                    walk(v, prop, prop)
                elif key in ("properties", "$defs", "items", "additionalProperties"):
                    walk(v, None, None)
                else:
                    walk(v, key, key)
        elif isinstance(node, yaml.SequenceNode):
            for v in node.value:
                walk(v, name, prop)
        elif isinstance(node, yaml.ScalarNode):
            line = node.start_mark.line + 1
            if node.tag.endswith((":int", ":float")):
                value = yaml.safe_load(node.value)
                if isinstance(value, (int, float)) and value == value and abs(value) != float("inf"):
                    out.append(Literal(path, line, abs(value), norm(name) if name else None, by_value=False))
            elif node.tag.endswith(":str"):
                out.extend(text_numbers(node.value, name, path, line))
                for m in re.finditer(r"\b([A-Za-z_]\w*)=(-?\d+(?:\.\d+)?)\b", node.value):  # a --config k=v
                    out.append(Literal(path, line, abs(float(m.group(2))), norm(m.group(1))))

    for doc in yaml.compose_all(text, Loader=yaml.SafeLoader):
        walk(doc, None, None)
    return out


def literals(path: Path, root: Path) -> list[Literal]:
    """Every number written in ``path`` (Python, a Snakemake file or YAML), with the name it is bound to."""
    rel = str(path.relative_to(root))
    text = path.read_text()
    if path.suffix == ".py":
        return _python_literals(text, rel)
    if path.suffix in (".yaml", ".yml"):
        return _yaml_literals(text, rel)
    return _workflow_literals(text, rel)


def walked_files(root: Path) -> list[Path]:
    """The package code (CLIs included), the scripts, the workflow (rules, Snakefiles, scripts)
    and the YAML of :data:`YAML_FILES`."""
    files = [p for pkg in PACKAGES for p in sorted((root / pkg).rglob("*.py"))]
    files += sorted((root / "workflow").rglob("*.py")) + sorted((root / "workflow").rglob("*.smk"))
    files += [p for p in (root / "Snakefile", root / "workflow" / "Snakefile") if p.is_file()]
    return files + [p for pattern in YAML_FILES for p in sorted(root.glob(pattern)) if p.is_file()]


def repeats(root: Path, sources=SOURCES, shared: dict | None = None) -> list[str]:
    """One line per repeat (module docstring): ``path:line: N (name) is the default of
    home:name``. ``shared``: {(path, name): reason} of definitions that restate a default on
    purpose (a stage that may not import the defining one)."""
    shared = shared or {}
    defaults: dict[float, dict[str, str]] = {}  # value -> {name: home}
    out = []
    for rel in sources:
        for d in definitions((root / rel).read_text(), rel):
            if d.value in TRIVIAL_BY_NAME:
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
            if lit.name in names and lit.value not in TRIVIAL_BY_NAME:
                out.append(f"{rel}:{lit.line}: {lit.value:g} ({lit.name}) is the default of "
                           f"{names[lit.name]}:{lit.name}")
            elif lit.by_value and distinctive(lit.value) and lit.value not in own:
                name, home = sorted(names.items())[0]
                out.append(f"{rel}:{lit.line}: {lit.value:g} is the default of {home}:{name}")
    return sorted(set(out))


def hand_written_defaults(root: Path) -> list[str]:
    """One line per argparse help text that writes its flag's default as a number
    (``help="... (default 500)"``), trivial numbers included: the help should say
    ``%(default)s`` (or format the constant), so that it cannot drift from the default."""
    out = []
    for path in walked_files(root):
        if path.suffix != ".py":
            continue
        rel = str(path.relative_to(root))
        for lit in _help_literals(ast.parse(path.read_text()), rel):
            if lit.name is not None:
                out.append(f"{rel}:{lit.line}: the help of {lit.name} writes its default {lit.value:g} by hand")
    return sorted(set(out))
