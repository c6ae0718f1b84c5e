"""docs/results.md is generated from the records and cannot drift from them.

``python -m experiments.results_doc`` writes the page from ``experiments/records/`` (the studies) and
``benchmarks/records/`` (the GPU's speed and memory); the committed page
must be exactly what the command writes today. A section whose record is missing is left out
and named with the command that makes it, never filled in; a record that cannot be read is a
one-line refusal.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from _cli import refused, run

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "experiments" / "records"
BENCH_RECORDS = ROOT / "benchmarks" / "records"
DOC = ROOT / "docs" / "results.md"
LLFF_HEADING = "## The field's LLFF 3-view protocol"


def _records_copy(dest: Path, leave_out: tuple[str, ...] = (), source: Path = RECORDS) -> Path:
    """The records the page reads, linked into ``dest`` (the sparse-view runs themselves are not
    read: summary.json holds their figures), less ``leave_out``."""
    for p in source.rglob("*"):
        rel = p.relative_to(source)
        if p.is_dir() or rel.parts[:2] == ("sparse_views", "runs") or any(
                str(rel).startswith(x) for x in leave_out):
            continue
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        (dest / rel).symlink_to(p)
    return dest


def test_committed_page_is_what_the_records_give(tmp_path):
    out = tmp_path / "results.md"
    proc = run(["-m", "experiments.results_doc", "--doc", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert out.read_text() == DOC.read_text(), (
        "docs/results.md differs from what the records give: run `python -m experiments.results_doc` and commit it")
    text = out.read_text()
    for headline in ("equal background, black", "`sparse` − floor", "3DGS, random points | 15.52",
                     "DropGaussian | 20.76", "Do the backends train to the same result?",
                     "VGGT at many frames on one GPU", LLFF_HEADING):
        assert headline in text, headline


def test_section_without_its_record_is_named_with_its_command_not_filled(tmp_path):
    records = _records_copy(tmp_path / "records", leave_out=("llff_protocol",))
    out = tmp_path / "results.md"
    proc = run(["-m", "experiments.results_doc", "--records", str(records), "--doc", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = out.read_text()
    assert LLFF_HEADING not in text
    line = next(ln for ln in text.splitlines() if ln.startswith("- The field's LLFF 3-view protocol:"))
    assert "no record `experiments/records/llff_protocol/runs/`" in line
    assert "python -m experiments.sparse_views --protocol experiments/llff_protocol/scenes.yaml" in line
    assert "| llff__flower |" not in text and "mean of 7" not in text  # no figure of the missing record
    # the other sections are still there, and the same as on the full page
    full = DOC.read_text()
    for heading in ("## Training recipes on scenes they were not tuned on", "## On one GPU"):
        assert heading in text and heading in full
    assert "left out (no record): The field's LLFF 3-view protocol" in proc.stdout


def test_gpu_sections_read_the_benchmarks_records(tmp_path):
    """The GPU sections come from ``--bench-records``: without its GPU records they are named
    with their command under ``benchmarks/records/``; the studies' sections are unchanged."""
    bench = _records_copy(tmp_path / "bench", leave_out=("gpu-",), source=BENCH_RECORDS)
    out = tmp_path / "results.md"
    proc = run(["-m", "experiments.results_doc", "--bench-records", str(bench), "--doc", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = out.read_text()
    assert "## On one GPU" not in text and "## VGGT at many frames on one GPU" not in text
    assert "- On one GPU: no record `benchmarks/records/gpu-*.json`; `python -m benchmarks --gpu`" in text
    assert "## The field's LLFF 3-view protocol" in text and "## Training recipes on scenes" in text


def test_unreadable_record_is_a_one_line_refusal_and_writes_nothing(tmp_path):
    records = _records_copy(tmp_path / "records", leave_out=("sparse_views/summary.json",))
    (records / "sparse_views" / "summary.json").write_text('{"measures_by_n": ')
    out = tmp_path / "results.md"
    proc = run(["-m", "experiments.results_doc", "--records", str(records), "--doc", str(out)])
    refused(proc, "summary.json", "not a readable JSON record")
    assert not out.exists()
    proc = run(["-m", "experiments.results_doc", "--records", str(tmp_path / "nowhere"), "--doc", str(out)])
    refused(proc, "nowhere", "does not exist")
    assert not out.exists()


def test_figures_without_a_record_point_at_sections_that_exist():
    from experiments.results_doc.page import UNRECORDED

    for what, command, doc, where in UNRECORDED:
        assert command.startswith("`"), what
        assert (doc is None) == (where is None), what
        if doc is None:
            continue
        headings = [ln.lstrip("#").strip() for ln in (ROOT / doc).read_text().splitlines() if ln.startswith("## ")]
        # cited by the heading's leading words, as the READMEs' own tables cite them
        assert any(h.startswith(where) for h in headings), (what, doc, where)
