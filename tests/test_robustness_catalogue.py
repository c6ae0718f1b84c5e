"""docs/robustness.md cannot rot: every test it names is collected by pytest.

The catalogue table (and the known-bugs table) is parsed; every backticked ``tests/...``
reference must be a node id that ``pytest --collect-only`` reports (a parametrised test may
be named without its ``[...]``). The catalogue must keep at least 140 cases, spread over the
stages the issue lists, with the input cases also run through every image-reading stage's
command line; each known-bug test must be a strict xfail.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "robustness.md"
REF = re.compile(r"`(tests/[^`\s]+\.py(?:::[^`\s]+)?)`")


def _tables() -> dict[str, list[list[str]]]:
    """{section heading: rows (cells) of its Markdown table, header and rule excluded}."""
    out: dict[str, list[list[str]]] = {}
    section = None
    for line in DOC.read_text().splitlines():
        if line.startswith("## "):
            section = line[3:].strip()
            out[section] = []
        elif section and line.startswith("|") and not re.match(r"^\|\s*-", line):
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            out[section].append(cells)
    return {k: rows[1:] for k, rows in out.items() if rows}  # drop each header row


def _catalogue() -> list[list[str]]:
    return _tables()["Catalogue"]


def _refs(rows: list[list[str]]) -> list[str]:
    return [r for row in rows for r in REF.findall(row[-1])]


@lru_cache(maxsize=1)
def _collected() -> frozenset[str]:
    """Node ids pytest collects from the files the catalogue names (one subprocess)."""
    files = sorted({r.split("::")[0] for r in _refs(_catalogue()) + _refs(_tables().get("Known bugs (strict xfails)", []))})
    missing = [f for f in files if not (ROOT / f).is_file()]
    assert not missing, f"docs/robustness.md names test files that do not exist: {missing}"
    proc = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                           *files], cwd=ROOT, capture_output=True, text=True, timeout=300)
    ids = frozenset(line.strip() for line in proc.stdout.splitlines() if "::" in line)
    assert ids, f"pytest collected nothing:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return ids


def _test_object(ref: str):
    """The function (or method) a node id names, imported from its file."""
    path, *names = ref.split("::")
    spec = importlib.util.spec_from_file_location(f"_catalogue_{Path(path).stem}", ROOT / path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    obj = module
    for name in names:
        obj = getattr(obj, name)
    return obj


def _is_collected(ref: str, ids: frozenset[str]) -> bool:
    return ref in ids or any(i.startswith(ref + "[") for i in ids)


def test_catalogue_has_enough_cases_over_every_stage():
    rows = _catalogue()
    assert len(rows) >= 140, f"only {len(rows)} cases"
    assert [int(r[0]) for r in rows] == list(range(1, len(rows) + 1)), "cases must be numbered 1..N"
    for r in rows:
        assert len(r) == 5 and all(r), f"row {r[0]} must fill # | Stage | Input | Expected | Test"
        assert REF.search(r[4]), f"row {r[0]} names no test"
    stages = " ".join(r[1] for r in rows).lower()
    for needed in ("image loading", "vggt preprocessing", "vggt outputs", "bridge", "rasterizer", "trainer",
                   "alignment", "metrics", "colmap baseline"):
        assert needed in stages, f"no case for {needed}"
    # bad input as users meet it: each stage command that reads images has its own CLI-level row
    for cmd in ("python -m vggt_init", "python -m evaluation.initialisers.colmap_baseline", "python -m splat_train",
                "python -m evaluation images"):
        cli_rows = [r for r in rows if cmd in r[1] and "tests/test_robustness_cli.py::" in r[4]]
        assert cli_rows, f"no command-line case for `{cmd}`"


def test_every_catalogued_test_is_collected():
    ids = _collected()
    stale = [r for r in _refs(_catalogue()) if not _is_collected(r, ids)]
    assert not stale, f"docs/robustness.md names tests that pytest does not collect: {stale}"


def test_known_bugs_are_strict_xfails_that_exist():
    rows = _tables().get("Known bugs (strict xfails)", [])
    ids = _collected()
    for row in rows:
        refs = REF.findall(row[-1])
        assert refs, f"known bug {row[0]} names no test"
        for ref in refs:
            assert _is_collected(ref, ids), f"known bug {row[0]}: {ref} is not collected"
            marks = getattr(_test_object(ref), "pytestmark", [])
            assert any(m.name == "xfail" and m.kwargs.get("strict") is True for m in marks), \
                f"{ref} must be marked xfail(strict=True)"


@pytest.mark.parametrize("ref", ["tests/test_robustness_catalogue.py::test_every_catalogued_test_is_collected",
                                 "tests/test_robustness_catalogue.py::test_catalogue_has_enough_cases_over_every_stage"])
def test_checker_sees_itself(ref):
    """The matcher works on known ids, and rejects a made-up one (so it can fail)."""
    ids = frozenset([ref, "tests/x.py::test_p[a]"])
    assert _is_collected(ref, ids)
    assert _is_collected("tests/x.py::test_p", ids)
    assert not _is_collected("tests/x.py::test_q", ids)
    assert not _is_collected(ref + "_renamed", ids)
