"""The page: its sections in a fixed order, how a missing record is shown, the formatting.

A :class:`Section` names its heading, the command that makes its figures and the records it
reads (a path under its records folder, globs allowed: ``experiments/records/`` for the studies,
``benchmarks/records/`` for the GPU's speed and memory, ``bench=True``); its renderer returns the body lines
(table first, then at most a few lines of fixed text), or ``None`` when its record is not
there. A section without its record is left out of the page and named, with its command, in
the closing list, beside the figures that have no record at all (:data:`UNRECORDED`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[2]
RECORDS = REPO / "experiments" / "records"
BENCH_RECORDS = REPO / "benchmarks" / "records"
DOC = REPO / "docs" / "results.md"
COMMAND = "python -m experiments.results_doc"

__all__ = ["Section", "RecordError", "load", "latest", "render_page", "iv", "table", "UNRECORDED"]


class RecordError(ValueError):
    """A record that cannot be read: the message names the file and what is wrong."""


@dataclass(frozen=True)
class Section:
    heading: str
    command: str | Callable[[Path], str]  # a callable builds it from the records
    record: str  # what it reads, relative to its records folder (for the missing-record line)
    render: Callable[[Path], list[str] | None]
    bench: bool = False  # its records are the benchmarks' (benchmarks/records/), not the studies'

    @property
    def folder(self) -> str:
        """Its records folder as the page names it."""
        return "benchmarks/records" if self.bench else "experiments/records"


def load(path: Path) -> dict:
    """One JSON record; :class:`RecordError` naming the file when it is not readable JSON."""
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordError(f"{path}: not a readable JSON record ({exc}); restore it from git or "
                          f"rerun the command that writes it") from None


def latest(records: Path, pattern: str) -> list[Path]:
    """Records matching ``pattern``, oldest first (their names sort by the day they were made)."""
    return sorted(records.glob(pattern))


def iv(d: dict | None, digits: int = 2) -> str:
    """A scene-level interval as ``+0.47 [-0.95, +1.90]`` (``n/a`` without a mean)."""
    if not d or d.get("mean") is None:
        return "n/a"
    f = f"{{:+.{digits}f}}".format
    return f(d["mean"]) if d.get("lo") is None else f"{f(d['mean'])} [{f(d['lo'])}, {f(d['hi'])}]"


def table(head: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table."""
    return (["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows])


def verdict(met: bool | None) -> str:
    return {True: "met", False: "not met", None: "n/a"}[met]


# Figures the project reports that no record holds: the page names their commands instead, and
# the page and section that keep their method and latest figures (benchmarks/README.md for speed
# and memory, experiments/README.md for the studies), where one does.
UNRECORDED = (
    ("the demo's wall time", "`make demo` (`scripts/demo.sh`)", "benchmarks/README.md", "Workflow, demo and test-suite wall time"),
    ("the test suite's time, serially and on both cores; CI from a clean clone",
     "`.venv/bin/python -m pytest -q`, `make test`, `.ci/run`", "benchmarks/README.md", "Workflow, demo and test-suite wall time"),
    ("the real-SLURM test", "`scripts/slurm_test.sh`", "benchmarks/README.md", "Workflow, demo and test-suite wall time"),
    ("the COLMAP train-only baseline's success count on real scenes",
     "`snakemake --cores 2 --configfile config/real_scenes.yaml`", None, None),
    ("the CPU rasterizer's speed", "`python benchmarks/bench_rasterizer.py`", "benchmarks/README.md", "Rasterizer and kernels"),
    ("VGGT-1B's forward on the CPU", "`python benchmarks/bench_vggt.py --frames 3 6 12`", "benchmarks/README.md", "VGGT on the CPU"),
    ("the paper's 10,000-iteration fern cell on the CPU", "`python benchmarks/bench_cell.py --iterations 10000`",
     "benchmarks/README.md", "Training speed on the CPU"),
    ("the `mvs` initialiser's depth accuracy, coverage, time and memory",
     "`python -m experiments.mvs_accuracy --scene FERN --out JSON`", "experiments/README.md", "The `mvs` initialiser's depth accuracy"),
    ("camera refinement under pose error (bundle adjustment, training-time refinement)",
     "`python experiments/pose_refinement.py --quick`", "experiments/README.md", "Camera refinement"),
    ("the browser viewer's agreement with the renderer, and its load time",
     "`.venv/bin/python -m pytest tests/test_view_browser.py`, `python benchmarks/bench_viewer.py`",
     "benchmarks/README.md", "Browser viewer open time"),
    ("gsplat's CUDA build without a GPU", "`python scripts/gsplat_build_check.py`", "benchmarks/README.md", "GPU"),
    ("the earlier fern-only recipe study (records in `experiments/records/recipe_study/`, made "
     "with a former Gaussian cap)", "`python experiments/recipe_study.py`", "experiments/README.md", "Training recipes"),
)

#: the line that marks the page this command wrote: ``--doc FILE`` replaces only a file that
#: holds it, or writes a new one (experiments.sparse_views.summary.check_doc)
GENERATED = f"Generated by `{COMMAND}`"

HEAD = [
    "# Results: the current figures and the command that makes each",
    "",
    f"{GENERATED} from the records under `experiments/records/` and",
    "`benchmarks/records/`; do not edit by hand",
    "(rerun the command after a record changes; `tests/test_results_doc.py` fails until then).",
    "Each section: the figures, the command that makes its records, what the figures are not.",
    "The method and protocol: `docs/reference.md`; the field's published figures with sources:",
    "`docs/field.md`; the studies: `experiments/README.md`; the speed and memory benchmarks, their",
    "method and machines: `benchmarks/README.md`.",
]


def command_of(s: Section, records: Path) -> str:
    return s.command(records) if callable(s.command) else s.command


def render_page(records: Path, bench_records: Path,
                sections: tuple[Section, ...]) -> tuple[str, list[Section]]:
    """The page's Markdown and the sections left out for want of their record; ``records``: the
    studies' records (``experiments/records`` or a copy), ``bench_records``: the benchmarks'."""
    lines, missing = list(HEAD), []
    for s in sections:
        folder = bench_records if s.bench else records
        body = s.render(folder)
        if body is None:
            missing.append(s)
            continue
        lines += ["", f"## {s.heading}", "", *body, "", f"Command: {command_of(s, folder)}"]
    lines += ["", "## Figures without a record here", "",
              "Measured by the commands below, which print them; no record under `experiments/records/` or "
              "`benchmarks/records/` holds them, so they are not on this page:", ""]
    lines += [f"- {s.heading}: no record `{s.folder}/{s.record}`; "
              f"{command_of(s, bench_records if s.bench else records)}" for s in missing]
    lines += [f"- {what}: {cmd}" + (f"; see `{doc}`, \"{where}\"" if doc else "")
              for what, cmd, doc, where in UNRECORDED]
    return "\n".join(lines) + "\n", missing
