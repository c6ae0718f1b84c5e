"""The README and the --help texts as a new user reads them: every file they point to exists.

* Every backticked repository path in README.md (``scripts/demo.sh``, ``docs/robustness.md``,
  ``workflow/scripts/views.py`` ...) exists in the clone.
* No --help text of a stage command cites a file that is not in the repository (it used to
  cite the protocol file of a folder beside the clone; the protocol is docs/reference.md now).
* The README's stage block turns split.json into the image lists the later commands read
  (``views.py names`` writes train.txt before ``--image-list train.txt`` is used) and says how
  long the demo takes.
* make install / demo / test use the clone's own .venv.
* Every command of the project in a README code block pastes into a shell as written (no
  ``[...]`` placeholder, no ``a|b`` pipe) and uses only flags its --help lists.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
_TOP = ("camio/", "vggt_init/", "bridge/", "splat_train/", "evaluation/", "workflow/", "docs/",
        "scripts/", "config/", "benchmarks/", "experiments/", "constraints/", "tests/", ".ci/")


def _repo_paths(text: str) -> list[str]:
    out = []
    for tok in re.findall(r"`([^`\s]+)`", text):
        tok = tok.rstrip(".,;:")
        if tok.startswith(_TOP) and "{" not in tok and "*" not in tok and "<" not in tok:
            out.append(tok)
    return sorted(set(out))


def test_readme_paths_exist():
    paths = _repo_paths(README)
    assert len(paths) >= 10, paths
    missing = [p for p in paths if not (ROOT / p.split("::")[0]).exists()]
    assert not missing, f"README.md names files that are not in the repository: {missing}"


def test_readme_stage_block_makes_the_image_lists_it_uses():
    block = README[README.index("## Stages, one command each"):]
    block = block[: block.index("```", block.index("```bash") + 7)]
    writes = block.index("views.py names --split work/scene/split.json")
    reads = block.index("--image-list work/train.txt")
    assert writes < reads
    assert "../data/fern" not in README
    assert re.search(r"demo.*takes about \d", README.replace("\n", " "))


@pytest.mark.parametrize("module", ["evaluation.initialisers.colmap_baseline", "vggt_init", "splat_train", "bridge",
                                    "camio", "evaluation"])
def test_help_texts_cite_no_file_outside_the_repository(module):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-m", module, "--help"], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for name in re.findall(r"\b([A-Z][A-Z_]+\.md)\b", proc.stdout):  # docs, not outputs (tables.md)
        assert list(ROOT.rglob(name)), f"`python -m {module} --help` cites {name}, not in the repository"
    assert "PROTOCOL" + ".md" not in proc.stdout  # spelt in two parts: no file of the repository names it


def test_make_targets_use_the_clones_own_venv():
    make = (ROOT / "Makefile").read_text()
    assert re.search(r"^VENV \?= \.venv$", make, re.M) and "PY := $(VENV)/bin/python" in make
    # what .ci/run runs through `make test`: the suite on every core, as the README says
    assert "$(PY) -m pytest -q -n auto --dist loadfile" in make
    assert "`-n auto --dist loadfile`" in README
    install = (ROOT / "scripts" / "install.sh").read_text()
    assert '-m venv' in install and 'PY="$VENV/bin/python"' in install
    assert "pip install" in install and "$BASE_PY -m pip" not in install
    dry = subprocess.run(["make", "-n", "test"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert dry.returncode == 0 and ".venv/bin/python -m pytest -q -n auto --dist loadfile" in dry.stdout


def test_readme_python_example_runs(tmp_path):
    """The README's Python API example runs as written (into ``work/`` of its working folder)."""
    block = README[README.index("```python") + len("```python"):]
    block = block[: block.index("```")]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert re.search(r"^\d+ seed points -> \d+ Gaussians: work/api/train/model.ply$", proc.stdout, re.M), proc.stdout
    assert (tmp_path / "work" / "api" / "train" / "train.json").is_file()


_SHELL_OPERATORS = {"|", "||", "&", "&&", ";", "<", ">", ">>", "(", ")"}


def readme_commands(readme: str) -> list[str]:
    """Every command line of the README's bash blocks that runs one of the project's own
    programs (``python -m <package>``, ``python <repo script>``), continuation lines joined and
    the trailing comment cut."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", readme, re.S):
        for line in re.sub(r"\\\n\s*", "", block).splitlines():
            code = line.partition("  #")[0].strip()
            if re.match(r"python (-m (camio|vggt_init|bridge|splat_train|evaluation)\b|(scripts|workflow)/)", code):
                out.append(code)
    return out


def test_readme_commands_paste_as_written():
    """Each of the project's commands in the README is one command in a shell: shlex reads it,
    no placeholder in brackets, no ``a|b`` that the shell would take for a pipe."""
    cmds = readme_commands(README)
    assert len(cmds) >= 20, cmds
    for cmd in cmds:
        lexer = shlex.shlex(cmd, posix=True, punctuation_chars=True)
        tokens = list(lexer)
        assert not _SHELL_OPERATORS & set(tokens), f"{cmd}: a shell operator in {sorted(_SHELL_OPERATORS & set(tokens))}"
        assert not any(t.startswith("[") or t.endswith("]") for t in shlex.split(cmd)), f"{cmd}: a [...] placeholder"


def _program(argv: list[str]) -> list[str]:
    """The part of ``argv`` that names the program and its subcommand (``python -m camio convert``)."""
    if argv[1] == "-m":
        sub = argv[3:4] if len(argv) > 3 and not argv[3].startswith("-") and argv[3].isidentifier() else []
        return [sys.executable, "-m", argv[2], *sub]
    sub = argv[2:3] if len(argv) > 2 and not argv[2].startswith("-") and argv[2].isidentifier() else []
    return [sys.executable, argv[1], *sub]


def test_readme_flags_exist_in_the_commands_help():
    """Every --flag of a README command appears in that command's --help, so the README cannot
    show a flag that the program refuses."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    flags: dict[tuple[str, ...], set[str]] = {}
    for cmd in readme_commands(README):
        argv = shlex.split(cmd)
        flags.setdefault(tuple(_program(argv)), set()).update(t.split("=")[0] for t in argv if t.startswith("--"))
    assert len(flags) >= 10, flags
    missing = []
    for program, used in flags.items():
        proc = subprocess.run([*program, "--help"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, (program, proc.stderr[-2000:])
        missing += [f"{' '.join(program[1:])} {f}" for f in sorted(used) if not re.search(rf"{re.escape(f)}\b", proc.stdout)]
    assert not missing, f"README flags that --help does not list: {missing}"
