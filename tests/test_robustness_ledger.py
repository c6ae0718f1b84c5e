"""The output rule's records cannot be fooled (runtime.outdir): a stage vouches for a file only
while it is what the stage wrote, and the rule's own files are never opened through a link.

Each case runs the command a user runs (``python ...`` in a subprocess) and checks the exit
code, the one error line and the user's files byte for byte.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from runtime.ledger import LEDGER, LOCK, MARKER

from _cli import ENV, ROOT, refused, run

VIEWS = str(ROOT / "workflow" / "scripts" / "views.py")


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "scene"
    proc = run(["-m", "camio", "synth", "--out", str(out), "--views", "9", "--width", "32"])
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture(scope="module")
def view(tmp_path_factory) -> dict:
    from _view_scene import write_view_scene

    return write_view_scene(tmp_path_factory.mktemp("view"), n=12, width=32, height=24)


def _render(view: dict, out: Path, names: list[str]) -> subprocess.CompletedProcess:
    lst = out.parent / f"list{len(names)}.txt"
    lst.write_text("\n".join(names) + "\n")
    return run(["-m", "splat_train", "render", "--model", str(view["model"]), "--cameras", str(view["cameras"]),
                "--image-list", str(lst), "--alpha", "--out", str(out)])


def _names(split: Path, out: Path) -> subprocess.CompletedProcess:
    return run([VIEWS, "names", "--split", str(split), "--n", "3", "--out", str(out)])


def _tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): (p.read_bytes() if p.is_file() and not p.is_symlink() else b"<>")
            for p in sorted(root.rglob("*"))}


# --- a record vouches for a file only while it matches ----------------------------------------

def test_a_file_output_the_user_replaced_is_never_overwritten(synth, tmp_path):
    """``views.py names`` reruns over its own list; once the user has put their own file
    where the list stood (same name), the rerun names it and leaves it alone."""
    out = tmp_path / "lists" / "train.txt"
    assert _names(synth / "split.json", out).returncode == 0
    assert _names(synth / "split.json", out).returncode == 0  # its own, unchanged: replaced
    out.unlink()
    out.write_text("the user's list\n")
    refused(_names(synth / "split.json", out), str(out), "has changed since `views names` wrote it")
    assert out.read_text() == "the user's list\n"


def test_a_render_the_user_replaced_stops_the_rerun(view, tmp_path):
    """A fresh stage removes its earlier run's files on a rerun, but only those that are still
    what it wrote: a user's file put in place of one is named, never removed."""
    out = tmp_path / "renders"
    assert _render(view, out, ["view00.png", "view01.png"]).returncode == 0
    (out / "view01.png").unlink()
    (out / "view01.png").write_bytes(b"the user's picture")
    refused(_render(view, out, ["view02.png"]), str(out / "view01.png"), "changed since")
    assert (out / "view01.png").read_bytes() == b"the user's picture" and (out / "view00.png").is_file()


def test_a_rerun_never_writes_over_a_file_that_was_there_before_it(view, tmp_path):
    """A file the user put beside the renders, under a name the next run renders, is refused
    when the run comes to write it (one line), never overwritten."""
    out = tmp_path / "renders"
    assert _render(view, out, ["view00.png"]).returncode == 0
    (out / "view03.png").write_bytes(b"the user's picture")
    refused(_render(view, out, ["view03.png"]), str(out / "view03.png"), "before it ran")
    assert (out / "view03.png").read_bytes() == b"the user's picture"


def test_a_copied_folder_is_still_the_stages(synth, tmp_path):
    """A copy of a stage's folder (new inodes and times) holds the same bytes: a rerun into it
    works."""
    copy = tmp_path / "copy"
    shutil.copytree(synth, copy, copy_function=shutil.copy)
    proc = run(["-m", "camio", "synth", "--out", str(copy), "--views", "9", "--width", "32"])
    assert proc.returncode == 0, proc.stderr


_KILLED = ("import os, signal, sys\nfrom runtime.outdir import prepare_out\n"
           "prepare_out(sys.argv[1], {}, 'camio synth', replaces=True)\nos.kill(os.getpid(), signal.SIGKILL)\n")


def test_a_replacing_stage_after_a_killed_run_keeps_what_the_user_added(tmp_path):
    """``camio synth`` killed before its folder was in place leaves only its marker; a file the
    user then puts there is named by the rerun, never deleted with the folder."""
    out = tmp_path / "scene"
    proc = subprocess.run([sys.executable, "-c", _KILLED, str(out)], cwd=ROOT, env=ENV, capture_output=True)
    assert proc.returncode == -signal.SIGKILL and (out / MARKER).is_file()
    (out / "notes.txt").write_text("mine")
    refused(run(["-m", "camio", "synth", "--out", str(out), "--views", "9", "--width", "32"]),
            str(out / "notes.txt"), "did not write")
    assert (out / "notes.txt").read_text() == "mine"


def test_the_lock_of_a_killed_writer_is_taken_over_with_one_log_line(tmp_path):
    """A writer killed with SIGKILL leaves its lock file (its pid in it); the kernel released the
    lock, so the next command takes it over, says so in one log line of the output rule's logger,
    and gives the lock up when it ends."""
    out = tmp_path / "scene"
    proc = subprocess.run([sys.executable, "-c", _KILLED, str(out)], cwd=ROOT, env=ENV, capture_output=True)
    assert proc.returncode == -signal.SIGKILL
    dead = (out / LOCK).read_text().strip()
    assert dead.isdigit(), dead
    rerun = run(["-m", "camio", "synth", "--out", str(out), "--views", "9", "--width", "32"])
    assert rerun.returncode == 0, rerun.stderr
    assert f"INFO runtime.outdir: taking over the lock of {out}: process {dead} has ended" in rerun.stderr
    assert not (out / LOCK).exists()


def test_a_fresh_rerun_logs_how_many_of_its_files_it_removed(view, tmp_path):
    """``splat_train render`` reruns into its folder: it first removes the files its earlier run
    recorded (one log line of the output rule's logger, naming the count, the stage and the
    folder), so the folder never mixes two runs."""
    out = tmp_path / "renders"
    assert _render(view, out, ["view00.png", "view01.png"]).returncode == 0
    lines = (out / MARKER).read_text().splitlines()
    assert lines[:2] == ["splat_train render", "#files"], lines
    files = [rec for rec in map(json.loads, lines[2:]) if len(rec) > 1]
    assert {"view00.png", "view01.png"} <= {rec[0] for rec in files}
    rerun = _render(view, out, ["view02.png"])
    assert rerun.returncode == 0, rerun.stderr
    assert (f"INFO runtime.outdir: removed {len(files)} files of the earlier `splat_train render` run from {out}"
            in rerun.stderr), rerun.stderr[-2000:]
    assert not (out / "view00.png").exists() and (out / "view02.png").is_file()


# --- a marker or ledger this version does not read ---------------------------------------------

@pytest.mark.parametrize("ledger, why", [("train.txt\tviews names\n", "older version"),
                                          ('["train.txt", "views names", 1]\n', "not a record"),
                                          ("\x00\x01garbage\n", "not a record")])
def test_a_ledger_it_cannot_read_is_refused_and_never_appended_to(synth, tmp_path, ledger, why):
    folder = tmp_path / "lists"
    folder.mkdir()
    (folder / LEDGER).write_text(ledger)
    refused(_names(synth / "split.json", folder / "train.txt"), str(folder / LEDGER), why)
    assert _tree(folder) == {LEDGER: ledger.encode()}


@pytest.mark.parametrize("marker", ["splat_train render\n#files\nview00.png\n",  # an older version: bare paths
                                    "splat_train render\nview00.png\n",  # older still: top-level names
                                    'splat_train render\n#files\n["../outside.png", 1, 2, 3, 4, "00"]\n'])
def test_a_marker_it_cannot_read_is_refused(view, tmp_path, marker):
    out = tmp_path / "renders"
    out.mkdir()
    (out / MARKER).write_text(marker)
    (out / "view00.png").write_bytes(b"a render, or the user's")
    before = _tree(out)
    refused(_render(view, out, ["view01.png"]), str(out / MARKER), "not a marker this version reads")
    assert _tree(out) == before


# --- no write through a link -------------------------------------------------------------------

@pytest.mark.parametrize("own", [MARKER, LOCK, LEDGER])
def test_a_link_where_the_rules_own_file_goes_is_refused(view, tmp_path, own):
    """A symbolic link named like the marker, the lock or the ledger, pointing at a user's
    file: refused with one line, the user's file untouched."""
    precious = tmp_path / "precious.txt"
    precious.write_text("mine")
    out = tmp_path / "renders"
    out.mkdir()
    (out / own).symlink_to(precious)
    refused(_render(view, out, ["view00.png"]), str(out / own), "symbolic link")
    assert precious.read_text() == "mine" and not list(out.glob("*.png"))


def test_a_link_for_the_ledger_of_a_file_output_is_refused(synth, tmp_path):
    precious = tmp_path / "precious.txt"
    precious.write_text("mine")
    folder = tmp_path / "lists"
    folder.mkdir()
    (folder / LEDGER).symlink_to(precious)
    refused(_names(synth / "split.json", folder / "train.txt"), str(folder / LEDGER), "symbolic link")
    assert precious.read_text() == "mine" and not (folder / "train.txt").exists()


def test_an_out_that_is_a_link_is_refused(view, synth, tmp_path):
    """``--out`` a link to a folder, or to a file, or a file in a linked folder: refused."""
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "linked").symlink_to(real)
    refused(_render(view, tmp_path / "linked", ["view00.png"]), str(tmp_path / "linked"), "symbolic link")
    assert not list(real.iterdir())
    (real / "list.txt").write_text("mine")
    (tmp_path / "list.txt").symlink_to(real / "list.txt")
    refused(_names(synth / "split.json", tmp_path / "list.txt"), "symbolic link")
    refused(_names(synth / "split.json", tmp_path / "linked" / "new.txt"), "symbolic link")
    assert _tree(real) == {"list.txt": b"mine"}


def test_records_name_each_file_with_its_stamp(view, tmp_path):
    """What a finished run leaves: the marker's records carry size, times, inode and hash; the
    ledger's lines carry the writer too."""
    out = tmp_path / "renders"
    assert _render(view, out, ["view00.png"]).returncode == 0
    lines = (out / MARKER).read_text().splitlines()
    assert lines[:2] == ["splat_train render", "#files"]
    recs = {r[0]: r for r in map(json.loads, lines[2:]) if len(r) > 1}  # files; a folder is its name alone
    assert set(recs) == {"view00.png", "alpha/view00.png"}  # the render and its opacity (camio.alpha)
    for name, rec in recs.items():
        st = (out / name).stat()
        assert rec[:5] == [name, st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns] and len(rec[5]) == 32
