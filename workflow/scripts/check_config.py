"""Check a workflow configuration against workflow/schemas/config.schema.yaml, one line per
problem, naming the key and, for an unknown key, the nearest valid one. The schema's enums of
the lists the code defines once (x-enum-from) and the limits it defines once (x-maximum-from)
are read from the code here.

    python workflow/scripts/check_config.py config.yaml [more.yaml ...] [--set KEY=YAML ...]

Later files and ``--set`` values update earlier ones key by key (as snakemake's
``--configfile`` and ``--config`` do). Exit 0 when valid, 2 (bad input) otherwise, before
anything is written. The workflow runs the same check (workflow/rules/config.smk).
"""
from __future__ import annotations

import copy
import difflib
import fnmatch
import sys
from pathlib import Path

import yaml

SCHEMA = Path(__file__).resolve().parents[1] / "schemas" / "config.schema.yaml"
REPO = Path(__file__).resolve().parents[2]
"""The repository this workflow belongs to: a results folder may not be it, hold it, or lie in its
own folders."""


def _merge(base: dict, new: dict) -> dict:
    out = dict(base)
    for k, v in new.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _where(path) -> str:
    return ".".join(str(p) for p in path) or "(top level)"


def _known(schema: dict, node: dict) -> list[str]:
    """The keys an object of the schema may have (following local $refs)."""
    while "$ref" in node:
        node = schema["$defs"][node["$ref"].rsplit("/", 1)[-1]]
    return sorted(node.get("properties", {}))


class _UniqueKeyLoader(yaml.SafeLoader):
    """A YAML loader that refuses a key given twice in one mapping (PyYAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: PyYAML's own error follows
                break
            if first is not None:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} is given twice (first at line {first + 1}); "
                    "only one is used: remove or merge the other", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path):
    """A YAML configuration file, with any key given twice in one mapping refused.

    Raises:
        ValueError: one line ``FILE:LINE: the key 'x' is given twice (first at line N) ...``.
    """
    text = Path(path).read_text()
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise ValueError(f"{where}: {exc.problem}") from None


def results_folder(results: str) -> Path:
    """The results folder a config's ``results`` names: ``~`` expanded, relative to the working
    directory (the workflow's), symbolic links resolved."""
    return Path(results).expanduser().resolve()


def _ignored(rel: Path, root: Path) -> bool:
    """Whether ``rel`` (relative to the repository ``root``) is, or lies in, a path the
    repository's ``.gitignore`` ignores (its output folders: ``results/``, ``results_photos/``).
    Plain patterns only (``!`` negations are not followed). Without a ``.gitignore`` (a copy
    that is no checkout) outputs cannot be told from the repository's files: every path is."""
    try:
        lines = (root / ".gitignore").read_text().splitlines()
    except OSError:
        return True
    parts = rel.parts
    for line in lines:
        pat = line.strip()
        if not pat or pat.startswith(("#", "!")):
            continue
        anchored = "/" in pat.strip("/") or pat.startswith("/")
        pat = pat.strip("/")
        for k in range(1, len(parts) + 1):
            if fnmatch.fnmatchcase("/".join(parts[:k]) if anchored else parts[k - 1], pat):
                return True
    return False


def _results_problem(config: dict) -> str | None:
    """The results folder: not empty, not the file system's root (every output would be
    planned at the top of the disk), not the repository or a folder holding it, and not
    inside the repository's own folders (the outputs would mix with its code and docs): a
    folder inside the repository must be one its ``.gitignore`` ignores (``results/``;
    :func:`_ignored`)."""
    results = config.get("results")
    if not isinstance(results, str):
        return None  # the schema's type check says it
    if not results.strip():
        return "results: the results folder is empty; name a folder (default: results)"
    folder = results_folder(results)
    if folder == Path(folder.anchor):
        return f"results: {results!r} is the file system's root; name a folder of its own (default: results)"
    if folder == REPO or folder in REPO.parents:
        return (f"results: {results!r} is {folder}, which is or holds the repository {REPO}: the outputs would "
                "mix with its code; name a folder of its own (default: results)")
    if REPO in folder.parents and not _ignored(folder.relative_to(REPO), REPO):
        return (f"results: {results!r} lies inside the repository {REPO}, in "
                f"{folder.relative_to(REPO).parts[0]}/, which its .gitignore does not set aside for outputs: "
                "the outputs would mix with its files; name a folder it ignores (default: results) or one "
                "outside it")
    return None


def enum_sources() -> dict[str, tuple]:
    """The lists the schema names (``x-enum-from: KEY``), each read from its one place; light
    modules only (no torch)."""
    from camio.scene import FORMATS
    from evaluation.initialisers import registry
    from runtime.modes import BRIDGE_MODES
    from splat_train.recipes import RECIPE_NAMES
    from vggt_init.defaults import POINT_SOURCES

    return {
        "initialisers": registry.NAMES,
        "study_initialisers": registry.studied(),
        "bridge_modes": BRIDGE_MODES,
        "recipes": RECIPE_NAMES,
        "vggt_point_sources": POINT_SOURCES,
        "dataset_formats": FORMATS,
    }


def maximum_sources() -> dict[str, int]:
    """The limits the schema names (``x-maximum-from: KEY``), each read from its one place."""
    from camio.limits import MAX_IMAGE_SIDE
    from splat_train.config import SEED

    return {"MAX_IMAGE_SIDE": MAX_IMAGE_SIDE, "TRAIN_SEED_MAX": int(SEED.hi)}


def load_schema(path: Path = SCHEMA) -> dict:
    """The config schema with every ``x-enum-from: KEY`` filled in as ``enum`` from
    :func:`enum_sources` (``None`` added where the key may be null), and every
    ``x-maximum-from: KEY`` as ``maximum`` from :func:`maximum_sources`.

    Raises:
        ValueError: a ``x-enum-from`` names no list, or a ``x-maximum-from`` no limit.
    """
    schema = yaml.safe_load(Path(path).read_text())
    sources = enum_sources()
    maxima = maximum_sources()

    def fill(node):
        if isinstance(node, dict):
            if "x-maximum-from" in node:
                key = node["x-maximum-from"]
                if key not in maxima:
                    raise ValueError(f"{path}: x-maximum-from {key!r} names no limit; known: {', '.join(maxima)}")
                node["maximum"] = maxima[key]
            if "x-enum-from" in node:
                key = node["x-enum-from"]
                if key not in sources:
                    raise ValueError(f"{path}: x-enum-from {key!r} names no list; known: {', '.join(sources)}")
                types = node.get("type", [])
                node["enum"] = list(sources[key]) + ([None] if "null" in types else [])
            for v in node.values():
                fill(v)
        elif isinstance(node, list):
            for v in node:
                fill(v)

    fill(schema)
    from evaluation.initialisers.registry import option_blocks

    for name, block in option_blocks().items():  # the options of initialisers the common rule runs
        if name in schema["properties"]:
            raise ValueError(f"{path}: the initialiser {name} has options in the registry and a block of its own "
                             "here; keep one (the registry's options are for the common rule)")
        schema["properties"][name] = block
    return schema


def fill_defaults(config: dict, schema: dict | None = None) -> dict:
    """``config`` with every default of the checked schema (:func:`load_schema`) filled in, in
    place, nested blocks included (as snakemake's ``validate(set_default=True)`` does with the
    schema file; here the enums and the initialisers' option blocks are the code's)."""
    import jsonschema

    schema = schema or load_schema()
    base = jsonschema.Draft202012Validator
    properties = base.VALIDATORS["properties"]

    def set_defaults(validator, props, instance, node):
        if isinstance(instance, dict):
            for key, sub in props.items():
                if "default" in sub:
                    instance.setdefault(key, copy.deepcopy(sub["default"]))
        yield from properties(validator, props, instance, node)

    jsonschema.validators.extend(base, {"properties": set_defaults})(schema).validate(config)
    return config


def config_problems(config: dict, schema: dict | None = None) -> list[str]:
    """One line per problem of ``config`` (against :func:`load_schema` unless ``schema`` is
    given); [] when it is valid."""
    import jsonschema

    schema = schema or load_schema()
    if not isinstance(config, dict):
        return [f"the configuration must be a mapping of keys, got {type(config).__name__}"]
    lines, suggested = [], set()
    validator = jsonschema.Draft202012Validator(schema)
    for err in sorted(validator.iter_errors(config), key=lambda e: (list(map(str, e.absolute_path)),
                                                                    e.validator != "additionalProperties")):
        where = _where(err.absolute_path)
        if err.validator == "additionalProperties":
            known = _known(schema, err.schema)
            for key in sorted(set(err.instance) - set(known)):
                near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
                suggested.update((tuple(map(str, err.absolute_path)), n) for n in near)
                hint = f"; did you mean '{near[0]}'?" if near else f"; valid keys: {', '.join(known)}"
                prefix = f"{where}." if err.absolute_path else ""
                lines.append(f"unknown key '{prefix}{key}'{hint}")
        elif err.validator == "required":
            missing = err.message.split("'")[1] if "'" in err.message else err.message
            if (tuple(map(str, err.absolute_path)), missing) in suggested:
                continue  # already said: the unknown key that is probably this one
            lines.append(f"missing key '{(where + '.') if err.absolute_path else ''}{missing}'")
        elif err.validator == "enum":
            near = difflib.get_close_matches(str(err.instance), [str(v) for v in err.validator_value], n=1)
            hint = f"; did you mean '{near[0]}'?" if near else \
                f"; valid: {', '.join(map(str, err.validator_value))}"
            lines.append(f"{where}: {err.instance!r} is not a valid value{hint}")
        else:
            lines.append(f"{where}: {err.message}")
    results = _results_problem(config)
    if results:
        lines.append(results)
    return list(dict.fromkeys(lines))


def load(paths: list[str], sets: list[str] = ()) -> dict:
    config: dict = {}
    for p in paths:
        data = read_yaml(p) or {}
        if not isinstance(data, dict):
            raise ValueError(f"{p}: the configuration must be a mapping of keys")
        config = _merge(config, data)
    for item in sets:
        key, _, value = item.partition("=")
        config = _merge(config, {key: yaml.safe_load(value)})
    return config


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="check_config.py", description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", help="configuration files, later ones updating earlier ones")
    p.add_argument("--set", action="append", default=[], metavar="KEY=YAML",
                   help="a top-level value, as snakemake --config KEY=VALUE (repeatable)")
    args = p.parse_args(argv)
    try:
        config = load(args.files, args.set)
    except (OSError, ValueError, yaml.YAMLError) as exc:
        print(f"config error: {exc}".splitlines()[0], file=sys.stderr)
        return 2
    problems = config_problems(config)
    for line in problems:
        print(f"config error ({', '.join(args.files)}): {line}", file=sys.stderr)
    return 2 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
