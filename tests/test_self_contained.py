"""The repository explains itself: no file cites a document outside it.

What the code and the docs rely on is written in ``docs/`` (``docs/reference.md``: the method
and the evaluation protocol; ``docs/field.md``: the field's numbers with their sources). So no
tracked file names the outside notes the project was built from, nor any path into the folder
beside the clone where this project's machines keep reference material. The one exception is
data: a file may name that folder's data (real scenes, official fixture sets) when it says, with
the marker ``machine-data``, that the path exists on this project's machines only; the tests'
one place for it is ``tests/_machine_data.py``. Records of measured runs (the JSON files under
``benchmarks/`` and ``experiments/``) keep the data paths of the machine that made them, as a record must.
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Spelt in two parts so that this file does not name them either.
OUTSIDE_DOCS = ("PROTOCOL" + ".md", "FIELD_FACTS" + ".md")
# A path into the folder beside the clone: written as a relative or absolute path, or built with
# pathlib from the repository root's parent.
OUTSIDE_PATH = re.compile(r"(?:\.\./|/work/)shared(?![\w-])"
                          r"|\.parents?(?:\[\d\])?(?:\.parent)*\s*/\s*[\"']shared[\"']")
# What may follow such a path: its data, nothing else (not its notes).
DATA_AFTER = re.compile(r"""^[\s"'/]*(?:data|vggt[\s"'/]+fixtures)\b""")
MARKER = re.compile(r"machine[- ]data", re.I)


def _tracked_text_files() -> list[Path]:
    proc = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                          cwd=ROOT, capture_output=True, timeout=60)
    if proc.returncode != 0:
        pytest.skip("not a git checkout: cannot list the repository's files")
    out = []
    for name in proc.stdout.decode().split("\0"):
        path = ROOT / name
        if not name or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:  # binary
            continue
        out.append(path)
    return out


FILES = _tracked_text_files()


def _is_record(rel: str) -> bool:
    return rel.startswith(("benchmarks/", "experiments/")) and rel.endswith(".json")


def test_the_listing_sees_the_repository():
    rels = {p.relative_to(ROOT).as_posix() for p in FILES}
    assert {"README.md", "docs/reference.md", "docs/field.md", "tests/_machine_data.py"} <= rels


def test_no_file_names_a_document_outside_the_repository():
    hits = []
    for path in FILES:
        text = path.read_text(errors="replace")
        for lineno, line in enumerate(text.splitlines(), 1):
            for name in OUTSIDE_DOCS:
                if name in line:
                    hits.append(f"{path.relative_to(ROOT)}:{lineno}: {name}")
    assert not hits, ("files cite documents that a clone does not have; cite docs/reference.md "
                      "or docs/field.md instead:\n" + "\n".join(hits))


def test_paths_outside_the_repository_are_marked_machine_data_only():
    hits = []
    for path in FILES:
        rel = path.relative_to(ROOT).as_posix()
        text = path.read_text(errors="replace")
        marked = bool(MARKER.search(text)) or _is_record(rel)
        for m in OUTSIDE_PATH.finditer(text):
            lineno = text.count("\n", 0, m.start()) + 1
            if not DATA_AFTER.match(text[m.end():m.end() + 40]):
                hits.append(f"{rel}:{lineno}: names {m.group(0)!r} but not its data")
            elif not marked:
                hits.append(f"{rel}:{lineno}: names {m.group(0)!r} without saying it is machine data")
    assert not hits, ("files name paths outside the repository (allowed only for data, in a file "
                      "that says `machine-data`):\n" + "\n".join(hits))


# The examples are spelt with UP, ABS and BESIDE so that this file names no such path itself.
@pytest.mark.parametrize("text, ok", [
    ("path: UP/data/scenes/llff__fern", True),
    ('X = ROOT.parent / BESIDE / "data" / "scenes"', True),
    ('X = Path(__file__).parents[1].parent / BESIDE / "vggt" / "fixtures"', True),
    ("see UP/STYLE.md", False),
    ("beside `UP`", False),
    ("ABS/hooks/before-stop", False),
])
def test_the_path_rule_itself(text, ok):
    text = text.replace("UP", ".." + "/shared").replace("ABS", "/work" + "/shared").replace("BESIDE", '"shared"')
    m = OUTSIDE_PATH.search(text)
    assert m is not None
    assert bool(DATA_AFTER.match(text[m.end():m.end() + 40])) is ok
    assert OUTSIDE_PATH.search("tests/data/vggt/shared/config.json") is None
