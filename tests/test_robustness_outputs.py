"""Nothing a user owns is lost: the output rule (runtime.outdir) in every command a user runs,
the workflow's views.py included, and in every rerun.

Each case runs the command line as a user does (``python ...`` in a subprocess where a
signal, a second process or the exit status matters; the command's ``main`` otherwise) and
checks the exit code, one error line naming the paths, no traceback, and the user's files
byte for byte.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from runtime.ledger import LOCK, MARKER
from runtime.names import check_name, check_name_list

from _cli import ENV, ROOT
from _cli import refused as _refused
from _cli import run as _run

VIEWS = ROOT / "workflow" / "scripts" / "views.py"


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    """A small scene written by ``camio synth`` (its marker lists every file it wrote)."""
    out = tmp_path_factory.mktemp("synth") / "scene"
    proc = _run(["-m", "camio", "synth", "--out", str(out), "--views", "9", "--width", "32"])
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture
def scene(synth, tmp_path) -> Path:
    dst = tmp_path / "s"
    shutil.copytree(synth, dst, symlinks=True)
    return dst


def _views(*args: str) -> list[str]:
    return [str(VIEWS), *args]


# --- views.py: the workflow's own script, run by users from the README -------------------------

def test_views_link_out_equal_to_images_keeps_every_image(scene):
    before = _tree(scene / "images")
    proc = _run(_views("link", "--split", str(scene / "split.json"), "--images", str(scene / "images"),
                       "--out", str(scene / "images")))
    _refused(proc, "is the input --images")
    assert _tree(scene / "images") == before


def test_views_link_into_a_users_folder_is_refused(scene, tmp_path):
    user = tmp_path / "u"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    proc = _run(_views("link", "--split", str(scene / "split.json"), "--images", str(scene / "images"),
                       "--out", str(user)))
    _refused(proc, str(user), "not empty")
    assert _tree(user) == {"notes.txt": b"mine"}


def test_views_names_never_replaces_the_split_or_a_users_file(scene, tmp_path):
    split = (scene / "split.json").read_bytes()
    proc = _run(_views("names", "--split", str(scene / "split.json"), "--n", "3", "--out", str(scene / "split.json")))
    _refused(proc, "is the input --split")
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    proc = _run(_views("names", "--split", str(scene / "split.json"), "--n", "3", "--out", str(notes)))
    _refused(proc, str(notes), "exists", "never replaces a file it did not write")
    assert (scene / "split.json").read_bytes() == split and notes.read_text() == "mine"


@pytest.mark.parametrize("name", ["../0002.png", "/etc/passwd", "a/b.png", "..", ""])
def test_views_link_refuses_a_split_name_that_leaves_the_folder(scene, tmp_path, name):
    data = json.loads((scene / "split.json").read_text())
    data["test"] = [name]
    bad = tmp_path / "split.json"
    bad.write_text(json.dumps(data))
    victim = tmp_path / "0002.png"
    victim.write_bytes(b"user's file")
    proc = _run(_views("link", "--split", str(bad), "--images", str(scene / "images"), "--out", str(tmp_path / "t")))
    _refused(proc, str(bad), "not a plain file name")
    assert victim.read_bytes() == b"user's file" and not (tmp_path / "t").exists()


def test_views_reruns_into_their_own_outputs_and_names_a_file_they_did_not_write(scene, tmp_path):
    split, images = str(scene / "split.json"), str(scene / "images")
    out, lst = tmp_path / "test_images", tmp_path / "train.txt"
    for _ in range(2):  # a rerun into its own outputs works
        assert _run(_views("link", "--split", split, "--images", images, "--out", str(out))).returncode == 0
        assert _run(_views("names", "--split", split, "--n", "3", "--out", str(lst))).returncode == 0
    assert len(lst.read_text().split()) == 3 and sorted(p.name for p in out.iterdir() if p.name != MARKER)
    (out / "mine.txt").write_text("keep")
    proc = _run(_views("link", "--split", split, "--images", images, "--out", str(out)))
    _refused(proc, "mine.txt", "did not write")
    assert (out / "mine.txt").read_text() == "keep"


def test_views_bad_inputs_are_one_line(scene, tmp_path):
    split, images = str(scene / "split.json"), str(scene / "images")
    folder = tmp_path / "a_folder"
    folder.mkdir()
    _refused(_run(_views("names", "--split", split, "--n", "3", "--out", str(folder))), "is a folder")
    _refused(_run(_views("names", "--split", str(scene / "images" / "0000.png"), "--n", "3",
                         "--out", str(tmp_path / "x.txt"))), "0000.png")
    _refused(_run(_views("notes", "--skipped", "{not json", "--out", str(tmp_path / "n.json"))), "--skipped")
    bad = tmp_path / "status.json"
    bad.write_text("[1, 2]")
    _refused(_run(_views("index", "--status", str(bad), "--out", str(tmp_path / "i.json"))), str(bad))
    dup = json.loads((scene / "split.json").read_text())
    dup["test"] = dup["test"] + dup["test"][:1]
    (tmp_path / "dup.json").write_text(json.dumps(dup))
    _refused(_run(_views("link", "--split", str(tmp_path / "dup.json"), "--images", images,
                         "--out", str(tmp_path / "t"))), "twice")


# --- camio split: a file --out ---------------------------------------------------------------

@pytest.mark.parametrize("target", ["images/0001.png", "sparse/0/cameras.txt", "synthetic.json"])
def test_camio_split_never_replaces_a_file_it_did_not_write(scene, target):
    before = (scene / target).read_bytes()
    proc = _run(["-m", "camio", "split", "--scene", str(scene), "--n", "3", "--out", str(scene / target)])
    _refused(proc, str(scene / target), "was")
    assert (scene / target).read_bytes() == before


def test_camio_split_replaces_the_split_the_scene_stage_wrote_and_its_own(scene):
    for _ in range(2):
        proc = _run(["-m", "camio", "split", "--scene", str(scene), "--n", "2", "--out", str(scene / "split.json")])
        assert proc.returncode == 0, proc.stderr
    assert list(json.loads((scene / "split.json").read_text())["train"]) == ["2"]


# --- reruns: file by file, in every subfolder ------------------------------------------------

@pytest.mark.parametrize("foreign, named", [("images/notes.txt", "images/notes.txt"), ("sparse/1/cameras.txt", "sparse/1"),
                                            ("gt/depth/mine.npy", "gt/depth/mine.npy"), ("extra/", "extra")])
def test_synth_rerun_keeps_a_foreign_file_in_any_subfolder(scene, foreign, named):
    path = scene / foreign.rstrip("/")
    if foreign.endswith("/"):
        path.mkdir()
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"the user's")
    before = _tree(scene)
    proc = _run(["-m", "camio", "synth", "--out", str(scene), "--views", "9", "--width", "32"])
    _refused(proc, str(scene / named), "did not write")
    assert _tree(scene) == before and path.exists()


def test_synth_rerun_into_its_own_folder_still_works(scene):
    proc = _run(["-m", "camio", "synth", "--out", str(scene), "--views", "9", "--width", "32"])
    assert proc.returncode == 0, proc.stderr
    marker = (scene / MARKER).read_text().splitlines()
    assert marker[:2] == ["camio synth", "#files"] and "images/0000.png" in _recorded(marker)


def _recorded(marker: list[str]) -> list[str]:
    """The paths a marker's record lines (after its two header lines) name."""
    return [json.loads(line)[0] for line in marker[2:]]


def test_convert_rerun_keeps_a_users_model_folder(synth, tmp_path):
    out = tmp_path / "prepared"
    args = ["-m", "camio", "convert", "--src", str(synth), "--out", str(out), "--n", "3"]
    assert _run(args).returncode == 0
    (out / "sparse" / "1").mkdir(parents=True)
    (out / "sparse" / "1" / "cameras.txt").write_text("# the user's model\n")
    _refused(_run(args), "sparse/1", "did not write")
    assert (out / "sparse" / "1" / "cameras.txt").read_text() == "# the user's model\n"


def _render(view: dict, out: Path, names: list[str]) -> subprocess.CompletedProcess:
    lst = out.parent / f"list{len(names)}.txt"
    lst.write_text("\n".join(names) + "\n")
    return _run(["-m", "splat_train", "render", "--model", str(view["model"]), "--cameras", str(view["cameras"]),
                 "--image-list", str(lst), "--alpha", "--out", str(out)])


@pytest.fixture(scope="module")
def view(tmp_path_factory) -> dict:
    from _view_scene import write_view_scene

    return write_view_scene(tmp_path_factory.mktemp("view"), n=60, width=32, height=24)


def test_render_rerun_clears_its_own_earlier_renders_and_keeps_the_users(view, tmp_path):
    out = tmp_path / "renders"
    assert _render(view, out, ["view00.png", "view01.png", "view02.png"]).returncode == 0
    (out / "mine.txt").write_text("keep")
    (out / ".stage").read_text()
    proc = _render(view, out, ["view03.png"])
    assert proc.returncode == 0, proc.stderr
    pngs = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.png"))
    assert pngs == ["alpha/view03.png", "view03.png"], pngs  # never a mix of two runs (the render and its alpha)
    assert (out / "mine.txt").read_text() == "keep"


_KILLED = ("import os, signal, sys\nfrom pathlib import Path\nfrom runtime.atomic import atomic_path\n"
           "from runtime.outdir import prepare_out\nout = Path(sys.argv[1])\n"
           "prepare_out(out, {}, 'splat_train render', fresh=True)\n"
           "for name in sys.argv[2:]:\n    with atomic_path(out / name) as tmp:\n        tmp.write_bytes(b'half a run')\n"
           "os.kill(os.getpid(), signal.SIGKILL)\n")


def _killed_render(out: Path, *names: str) -> None:
    """What a render killed (SIGKILL: no ``finally`` runs) after writing ``names`` leaves."""
    proc = subprocess.run([sys.executable, "-c", _KILLED, str(out), *names], cwd=ROOT, env=ENV,
                          capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr


def test_render_after_an_unfinished_run_removes_what_that_run_wrote_and_keeps_the_users(view, tmp_path):
    """A run that did not finish (killed) recorded each file as it wrote it; the next run
    removes those, so half a run never mixes with a whole one, and keeps everything the user
    added to the folder after the kill."""
    out = tmp_path / "renders"
    assert _render(view, out, ["view00.png", "view01.png"]).returncode == 0
    _killed_render(out, "view02.png", "sub/view04.png")
    (out / "view05.png").write_bytes(b"the user's, added after the kill")
    (out / "mine").mkdir()
    (out / "mine" / "notes.txt").write_text("mine")
    proc = _render(view, out, ["view03.png"])
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*.png")) == [
        "alpha/view03.png", "view03.png", "view05.png"]
    assert (out / "view05.png").read_bytes() == b"the user's, added after the kill" and not (out / "sub").exists()
    assert (out / "mine" / "notes.txt").read_text() == "mine"


# --- one writer per output folder ------------------------------------------------------------

_HOLD = ("import sys, time\nfrom runtime.outdir import prepare_out\n"
         "prepare_out(sys.argv[1], {}, 'splat_train render', fresh=True)\nprint('ready', flush=True)\ntime.sleep(60)\n")


def test_a_second_writer_is_refused_naming_the_holder(view, tmp_path):
    out = tmp_path / "renders"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(out)], stdout=subprocess.PIPE, text=True,
                              cwd=ROOT, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "ready"
        proc = _render(view, out, ["view00.png"])
        _refused(proc, str(out), f"pid {holder.pid}", "another process")
        assert not list(out.rglob("*.png"))
    finally:
        holder.kill()
        holder.wait()
    # killed: the kernel released its lock; the next writer takes it over and removes the file
    assert (out / LOCK).exists()
    proc = _render(view, out, ["view00.png"])
    assert proc.returncode == 0, proc.stderr
    assert (out / "view00.png").is_file() and not (out / LOCK).exists()


def test_two_trainers_on_one_folder_one_is_refused(tmp_path):
    """The lock is taken by every stage's prepare_out: the trainer's too."""
    out = tmp_path / "train"
    holder = subprocess.Popen([sys.executable, "-c", _HOLD.replace("splat_train render", "splat_train"), str(out)],
                              stdout=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "ready"
        from runtime.ledger import OutputFolderError
        from runtime.outdir import prepare_out

        with pytest.raises(OutputFolderError, match=f"pid {holder.pid}"):
            prepare_out(out, {}, "splat_train")
    finally:
        holder.kill()
        holder.wait()


# --- signals ---------------------------------------------------------------------------------

def _default_stops() -> None:
    """In the child: SIGTERM, SIGINT, SIGHUP at their defaults (an ignored one stays ignored)."""
    for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP])
def test_a_stopped_command_leaves_no_temporary_folder(tmp_path, sig):
    out = tmp_path / "scene"
    proc = subprocess.Popen([sys.executable, "-m", "camio", "synth", "--out", str(out), "--views", "60",
                             "--width", "96"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT, env=ENV, preexec_fn=_default_stops)
    deadline = time.time() + 60
    while time.time() < deadline and not list(tmp_path.glob(".scene.*.tmp")):
        time.sleep(0.02)
    assert list(tmp_path.glob(".scene.*.tmp")), "the command never started writing"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and "stopped by" in err
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")], list(tmp_path.iterdir())
    assert not out.exists() or not [p for p in out.iterdir() if p.name != MARKER]


# --- names read from files ---------------------------------------------------------------------

@pytest.mark.parametrize("name", ["../x.png", "/abs.png", "a/b.png", "a\\b.png", "..", ".", "", "x\0.png", "a\nb",
                                  "bad\udcff.png"])
def test_a_name_that_is_not_a_plain_file_name_is_refused(name):
    with pytest.raises(ValueError, match="not a plain file name"):
        check_name(name, "image name", "list.txt")


def test_a_name_listed_twice_is_refused_with_both_places():
    with pytest.raises(ValueError, match=r"'b.png' is listed twice \(entries 2 and 3\)"):
        check_name_list(["a.png", "b.png", "b.png"], "list.txt")


def test_trainer_image_list_with_a_duplicate_is_one_line(view, tmp_path):
    lst = tmp_path / "train.txt"
    lst.write_text("view00.png\nview01.png\nview00.png\n")
    (tmp_path / "images").mkdir()
    proc = _run(["-m", "splat_train", "--seed", str(view["seed"]), "--cameras", str(view["cameras"]),
                 "--images", str(tmp_path / "images"), "--image-list", str(lst), "--out", str(tmp_path / "o")])
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "listed twice" in proc.stderr and str(lst) in proc.stderr


def test_lpips_convert_keeps_to_the_output_rule(tmp_path):
    """The weight converter writes two files into a folder: never over its --src, never over
    a file of that name it did not write (weights that load as such count as its own)."""
    src = tmp_path / "src"
    src.mkdir()
    proc = _run(["-m", "evaluation.metrics.lpips_convert", "--src", str(src), "--out", str(src / "alex.safetensors"),
                 "--nets", "alex"])
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    user = tmp_path / "cache"
    user.mkdir()
    (user / "alex.safetensors").write_bytes(b"the user's file")
    proc = _run(["-m", "evaluation.metrics.lpips_convert", "--src", str(src), "--out", str(user), "--nets", "alex"])
    _refused(proc, str(user / "alex.safetensors"), "exists")
    assert (user / "alex.safetensors").read_bytes() == b"the user's file"


def test_a_stage_rerun_refuses_a_foreign_file_inside_a_folder_it_wrote(synth, tmp_path):
    """Every stage records what it wrote (the marker's ``#files``); a rerun that would replace
    one of its folders whole (``sparse/0``) refuses while a user's file lies inside it, and a
    file beside its outputs at the top level stays through the rerun."""
    out = tmp_path / "posed"
    args = ["-m", "evaluation.initialisers.posed", "--scene", str(synth), "--names", "0001.png", "0002.png",
            "0003.png", "--out", str(out)]
    assert _run(args).returncode == 0
    written = (out / MARKER).read_text().splitlines()
    assert written[:2] == ["evaluation.posed", "#files"] and "sparse/0/cameras.txt" in _recorded(written)
    (out / "notes.txt").write_text("beside")
    proc = _run(args)
    assert proc.returncode == 0, proc.stderr
    assert (out / "notes.txt").read_text() == "beside" and "notes.txt" not in (out / MARKER).read_text()
    (out / "sparse" / "0" / "mine.txt").write_text("inside")
    _refused(_run(args), str(out / "sparse" / "0" / "mine.txt"), "inside a folder")
    assert (out / "sparse" / "0" / "mine.txt").read_text() == "inside"
