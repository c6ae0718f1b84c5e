"""The output-folder rule (runtime.outdir) through every stage command's ``main``.

For each stage command: an ``--out`` equal to an input, inside an input or holding an input
is refused with exit code 2 and one error line naming both paths, and the input is left
untouched; a non-empty folder the stage did not create is refused and left untouched. A
rerun of a stage into its own folder works, an empty pre-existing folder is accepted, and a
file the user put into a stage's folder is never deleted by the stage.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from runtime.ledger import MARKER


def _tree(root: Path) -> dict[str, bytes]:
    """{relative path: bytes} of every file under ``root`` (the input's full contents)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _inputs(tmp: Path) -> dict[str, Path]:
    """A tiny input folder (images/ with one file, a model folder, a list, a PLY name)."""
    images = tmp / "in" / "images"
    images.mkdir(parents=True)
    (images / "a.png").write_bytes(b"not read: the rule is checked before any input is read")
    model = tmp / "in" / "model"
    model.mkdir()
    (model / "cameras.txt").write_text("# untouched\n")
    lst = tmp / "in" / "train.txt"
    lst.write_text("a.png\n")
    return {"images": images, "model": model, "list": lst, "root": tmp / "in"}


def _main(module: str):
    import importlib

    return importlib.import_module(module).main


# (name, module, argv builder: (inputs, out) -> argv, the input path that --out is set to)
def _stages():
    return [
        ("camio convert", "camio.__main__", lambda i, o: ["convert", "--src", str(i["root"]), "--out", str(o)], "root"),
        ("camio split", "camio.__main__", lambda i, o: ["split", "--scene", str(i["root"]), "--manifest", str(i["list"]),
                                                      "--out", str(o)], "list"),
        ("bridge", "bridge.__main__", lambda i, o: ["--colmap", str(i["model"]), "--images", str(i["images"]),
                                                    "--out", str(o)], "model"),
        ("vggt_init", "vggt_init.__main__", lambda i, o: ["--images", str(i["images"]), "--out", str(o)], "images"),
        ("colmap_baseline", "evaluation.initialisers.colmap_baseline",
         lambda i, o: ["--images", str(i["images"]), "--names", "a.png", "--out", str(o)], "images"),
        ("posed", "evaluation.initialisers.posed",
         lambda i, o: ["--scene", str(i["root"]), "--names", "a.png", "--out", str(o)], "root"),
        ("ba_init", "evaluation.initialisers.ba_init",
         lambda i, o: ["--init", str(i["model"]), "--images", str(i["images"]), "--image-list", str(i["list"]),
                       "--out", str(o)], "model"),
        ("evaluation pose", "evaluation.__main__",
         lambda i, o: ["pose", "--pred", str(i["model"]), "--ref", str(i["model"]), "--names", str(i["list"]),
                       "--out", str(o)], "list"),
        ("evaluation images", "evaluation.__main__",
         lambda i, o: ["images", "--pred", str(i["images"]), "--gt", str(i["images"]), "--out", str(o)], "images"),
        ("evaluation floor", "evaluation.__main__",
         lambda i, o: ["floor", "--images", str(i["images"]), "--train-names", str(i["list"]), "--gt",
                       str(i["images"]), "--out", str(o)], "images"),
        ("evaluation align", "evaluation.__main__",
         lambda i, o: ["align", "--pred", str(i["model"]), "--ref", str(i["model"]), "--train-names",
                       str(i["list"]), "--out", str(o)], "model"),
        ("evaluation floaters", "evaluation.__main__",
         lambda i, o: ["floaters", "--model", f"final={i['list']}", "--align", str(i["list"]), "--scene",
                       str(i["root"]), "--out", str(o)], "list"),
        ("evaluation tables", "evaluation.__main__",
         lambda i, o: ["tables", "--results", str(i["root"]), "--out", str(o)], "root"),
        ("evaluation plots", "evaluation.__main__",
         lambda i, o: ["plots", "--results", str(i["root"]), "--out", str(o)], "root"),
        ("evaluation report", "evaluation.__main__",
         lambda i, o: ["report", "--results", str(i["root"]), "--out", str(o)], "root"),
        ("evaluation.initialisers.oracle", "evaluation.initialisers.oracle",
         lambda i, o: ["--scene", str(i["root"]), "--names", "a.png", "--out", str(o)], "root"),
        ("splat_train", "splat_train.__main__",
         lambda i, o: ["--seed-ply", str(i["list"]), "--cameras", str(i["model"]), "--images", str(i["images"]),
                       "--out", str(o)], "images"),
        ("splat_train render", "splat_train.__main__",
         lambda i, o: ["render", "--model", str(i["list"]), "--cameras", str(i["model"]), "--images",
                       str(i["images"]), "--out", str(o)], "images"),
    ]


STAGES = _stages()
IDS = [s[0] for s in STAGES]


def _error_lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if " ERROR " in ln]


@pytest.mark.parametrize("stage", STAGES, ids=IDS)
def test_out_equal_to_an_input_is_refused(tmp_path, capsys, stage):
    name, module, argv, which = stage
    inp = _inputs(tmp_path)
    before = _tree(inp["root"])
    rc = _main(module)(argv(inp, inp[which]))
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = _error_lines(err)
    assert len(lines) == 1 and "Traceback" not in err, err
    assert f"--out {inp[which]}" in lines[0] and "is the input" in lines[0], lines[0]
    assert _tree(inp["root"]) == before, "an input was changed"


@pytest.mark.parametrize("stage", [s for s in STAGES if s[3] != "root"], ids=[s[0] for s in STAGES if s[3] != "root"])
def test_out_holding_an_input_is_refused(tmp_path, capsys, stage):
    """--out set to the parent of an input (e.g. the folder above the photos)."""
    name, module, argv, which = stage
    inp = _inputs(tmp_path)
    (inp["root"] / "notes.txt").write_text("mine")
    before = _tree(inp["root"])
    rc = _main(module)(argv(inp, inp["root"]))
    err = capsys.readouterr().err
    assert rc == 2, err
    line, = _error_lines(err)
    assert f"--out {inp['root']}" in line and ("contains the input" in line or "is the input" in line), line
    assert _tree(inp["root"]) == before


@pytest.mark.parametrize("stage", [s for s in STAGES if s[0] not in ("camio split", "evaluation pose", "evaluation images",
                                                                      "evaluation floor", "evaluation floaters")],
                         ids=[s[0] for s in STAGES if s[0] not in ("camio split", "evaluation pose", "evaluation images",
                                                                   "evaluation floor", "evaluation floaters")])
def test_non_empty_folder_not_made_by_the_stage_is_refused(tmp_path, capsys, stage):
    name, module, argv, which = stage
    inp = _inputs(tmp_path)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    rc = _main(module)(argv(inp, out))
    err = capsys.readouterr().err
    assert rc == 2, err
    line, = _error_lines(err)
    assert f"--out {out}" in line and "not empty" in line and "thesis.tex" in line, line
    assert sorted(p.name for p in out.iterdir()) == ["thesis.tex"]
    assert (out / "thesis.tex").read_text() == "years of work"


def test_out_inside_an_input_is_refused(tmp_path, capsys):
    """``splat_train render --out images/renders``: never write into the ground truth."""
    inp = _inputs(tmp_path)
    out = inp["images"] / "renders"
    rc = _main("splat_train.__main__")(["render", "--model", str(inp["list"]), "--cameras", str(inp["model"]),
                                        "--images", str(inp["images"]), "--out", str(out)])
    line, = _error_lines(capsys.readouterr().err)
    assert rc == 2 and "lies inside the input --images" in line
    assert not out.exists()


def test_synth_rerun_into_its_own_folder_and_an_empty_folder(tmp_path, capsys):
    from camio.__main__ import main

    out = tmp_path / "synth"
    out.mkdir()  # an empty folder, as Snakemake makes it: fine
    argv = ["synth", "--out", str(out), "--views", "3", "--width", "16"]
    assert main(argv) == 0
    assert (out / MARKER).read_text().splitlines()[0] == "camio synth"
    assert main(argv) == 0, capsys.readouterr().err  # a rerun into its own folder
    (out / ".snakemake_timestamp").write_text("")  # Snakemake's, after a directory() output
    assert main(argv) == 0, capsys.readouterr().err
    (out / "notes.txt").write_text("mine")
    assert main(argv) == 2  # the rerun would replace the folder: it refuses instead
    line, = _error_lines(capsys.readouterr().err)
    assert "notes.txt" in line and "did not write" in line
    assert (out / "notes.txt").read_text() == "mine"


def test_another_stage_folder_is_refused(tmp_path, capsys):
    from camio.__main__ import main

    out = tmp_path / "synth"
    assert main(["synth", "--out", str(out), "--views", "3", "--width", "16"]) == 0
    inp = _inputs(tmp_path)
    rc = _main("evaluation.__main__")(["plots", "--results", str(inp["root"]), "--out", str(out)])
    line, = _error_lines(capsys.readouterr().err)
    assert rc == 2 and "was written by `camio synth`" in line


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root ignores permissions")
def test_read_only_out_is_one_line(tmp_path, capsys):
    from camio.__main__ import main

    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    try:
        rc = main(["synth", "--out", str(parent / "synth"), "--views", "3", "--width", "16"])
    finally:
        parent.chmod(0o755)
    err = capsys.readouterr().err
    line, = _error_lines(err)
    assert rc == 2 and "cannot write --out" in line and "Traceback" not in err


def test_unwritable_out_is_one_line_whoever_runs_it(tmp_path, capsys, monkeypatch):
    """The same refusal when the folder cannot be made (as root, chmod does not stop writes:
    the failure is injected where the rule creates the folder)."""
    import pathlib

    from camio.__main__ import main

    out = tmp_path / "ro" / "synth"
    real = pathlib.Path.mkdir

    def deny(self, *a, **k):
        if self == out:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *a, **k)

    monkeypatch.setattr(pathlib.Path, "mkdir", deny)
    rc = main(["synth", "--out", str(out), "--views", "3", "--width", "16"])
    err = capsys.readouterr().err
    line, = _error_lines(err)
    assert rc == 2 and f"cannot write --out {out}: Permission denied" in line and "Traceback" not in err


def test_out_reaching_an_input_through_a_symlink_is_refused(tmp_path, capsys):
    """Paths are compared after resolving links: a link to the images is the images."""
    inp = _inputs(tmp_path)
    link = tmp_path / "renders"
    link.symlink_to(inp["images"], target_is_directory=True)
    before = _tree(inp["root"])
    rc = _main("splat_train.__main__")(["render", "--model", str(inp["list"]), "--cameras", str(inp["model"]),
                                        "--images", str(inp["images"]), "--out", str(link / ".")])
    line, = _error_lines(capsys.readouterr().err)
    assert rc == 2 and "is the input --images" in line
    assert _tree(inp["root"]) == before


def test_split_json_may_go_into_the_scene_folder_but_never_over_an_input(tmp_path, capsys):
    """``camio split --scene S --out S/split.json`` is the scene layout; over the manifest it is refused."""
    from camio.__main__ import main

    scene = tmp_path / "scene"
    for i in range(9):
        (scene / "images").mkdir(parents=True, exist_ok=True)
        (scene / "images" / f"{i:02d}.png").write_bytes(b"")
    assert main(["split", "--scene", str(scene), "--n", "3", "--out", str(scene / "split.json")]) == 0
    assert (scene / "split.json").is_file()
    manifest = scene / "split.json"
    before = manifest.read_bytes()
    assert main(["split", "--scene", str(scene), "--manifest", str(manifest), "--out", str(manifest)]) == 2
    assert "is the input --manifest" in capsys.readouterr().err and manifest.read_bytes() == before


def test_workflow_logs_inside_out_count_as_empty_except_for_a_replacing_stage(tmp_path, capsys):
    """Snakemake makes ``n3/oracle/logs/`` (the rule's log:) before the job: the stage writes
    beside it; ``camio synth``, which replaces its folder whole, refuses rather than delete it."""
    from camio.__main__ import main

    inp = _inputs(tmp_path)
    out = tmp_path / "run"
    (out / "logs").mkdir(parents=True)
    (out / "logs" / "oracle_init.log").write_text("")
    failed = inp["root"] / "synthetic" / "s" / "n3" / "colmap"  # a run, so that there is something to plot
    failed.mkdir(parents=True)
    (failed / "status.json").write_text('{"success": false, "reason": "no model"}')
    rc = _main("evaluation.__main__")(["plots", "--results", str(inp["root"]), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    assert (out / "logs" / "oracle_init.log").exists()
    synth = tmp_path / "synth"
    (synth / "logs").mkdir(parents=True)
    assert main(["synth", "--out", str(synth), "--views", "3", "--width", "16"]) == 2
    assert "not empty" in capsys.readouterr().err and (synth / "logs").is_dir()
