"""Commands as a hostile user (or a scheduler) runs them: a stop signal while a command is still
loading, paths that name a file where a folder belongs and the other way round, output paths
under a file, array headers that claim more than their file holds, broken JSON, odd names.
Every bad input is exit 2, one line naming the value and what to do, nothing written; every
legitimate one works (docs/robustness.md)."""

from __future__ import annotations

import io
import json
import os
import random
import signal
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest
from numpy.lib import format as npy_format

from _cli import ENV, ROOT, refused, run
from _view_scene import make_cameras, make_model
from camio.colmap import write_text_model
from camio.ply import write_gaussian_ply


def _listing(root) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    """A small synthetic scene (camio synth), a trained-looking model and its cameras."""
    root = tmp_path_factory.mktemp("hostile")
    p = run(["-m", "camio", "synth", "--out", str(root / "scene"), "--views", "6", "--width", "48", "-q"])
    assert p.returncode == 0, p.stderr
    c = make_model(30)
    c.sh_rest = np.clip(c.sh_rest, -0.99, 0.99)
    (root / "afile").write_text("hi\n")
    (root / "empty").mkdir()
    return {"root": root, "scene": root / "scene", "model": write_gaussian_ply(root / "model.ply", c),
            "cams": write_text_model(root / "cams", make_cameras(48, 36, 4)), "afile": root / "afile",
            "empty": root / "empty"}


def _npy_header(shape, dtype="<f4", data: bytes = b"\0" * 64) -> bytes:
    b = io.BytesIO()
    npy_format.write_array_header_1_0(b, {"descr": dtype, "fortran_order": False, "shape": shape})
    return b.getvalue() + data


# -- a stop while the command loads ------------------------------------------------------------

EARLY = [  # (id, argv after python; @out: the output it would write)
    ("camio", ["-m", "camio", "synth", "--views", "4", "--width", "32", "--out", "@out"]),
    ("splat_train", ["-m", "splat_train", "export", "--format", "splat", "--out", "@out/m.splat", "@model"]),
    ("bridge", ["-m", "bridge", "--colmap", "@scene/sparse/0", "--out", "@out"]),
    ("evaluation", ["-m", "evaluation", "pose", "--pred", "@scene/sparse/0", "--ref", "@scene/sparse/0",
                    "--out", "@out/pose.json"]),
    ("vggt_init", ["-m", "vggt_init", "--images", "@scene/images", "--out", "@out"]),
    ("photos", ["scripts/photos.py", "@scene/images", "--out", "@out", "-n"]),
]


def _stop_signals_default() -> None:
    """In the child: the stop signals at their defaults, whatever the test runner inherited (a
    background job ignores SIGINT, ``nohup`` SIGHUP; a command keeps a signal ignored at start)."""
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)


def _started(proc: subprocess.Popen, first: str) -> list[str]:
    """Read ``-X importtime`` lines until the one after ``first`` (the module that installs the
    handlers): the command's own code has run past that point."""
    seen, lines = False, []
    for line in proc.stderr:
        lines.append(line)
        if seen:
            return lines
        seen = line.startswith("import time:") and line.split("|")[-1].strip() == first
    raise AssertionError("".join(lines[-20:]))


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("case,argv", EARLY, ids=[c[0] for c in EARLY])
def test_a_stop_while_the_command_loads_is_one_line(scene, tmp_path, case, argv, sig):
    """The signal comes right after the command's first line (before numpy, torch or pycolmap
    are imported) and 10-60 ms later, during those imports: one line, exit 128 + the signal, no
    traceback, nothing written. (Within the first few ms, before any line of the project runs,
    the interpreter's own defaults answer.)"""
    rng = random.Random(f"{case}{sig}")
    for delay in (0.0, rng.uniform(0.01, 0.06)):  # the second inside numpy's import or the next
        out = tmp_path / f"out{delay:.3f}"
        args = [str(scene["model"]) if a == "@model" else a.replace("@scene", str(scene["scene"]))
                .replace("@out", str(out)) for a in argv]
        proc = subprocess.Popen([sys.executable, "-X", "importtime", *args], cwd=ROOT, env=ENV, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=_stop_signals_default)
        try:
            head = _started(proc, "runtime.stops")
            time.sleep(delay)
            proc.send_signal(sig)
            stdout, rest = proc.communicate(timeout=60)
        finally:
            proc.kill()
        err = [ln for ln in head + rest.splitlines(keepends=True) if not ln.startswith("import time:")]
        text = "".join(err)
        assert proc.returncode == 128 + sig, (delay, proc.returncode, text[-2000:])
        assert "Traceback" not in text and "KeyboardInterrupt" not in text, text[-2000:]
        lines = [ln for ln in err if ln.strip()]
        assert len(lines) == 1 and f"stopped by {sig.name}" in lines[0], text[-2000:]
        assert not out.exists(), _listing(out)


# -- file and folder mix-ups -------------------------------------------------------------------

def _video(scene, video, *extra):
    return run(["-m", "splat_train", "render", "--model", str(scene["model"]), "--cameras", str(scene["cams"]),
                "--width", "32", "--height", "24", "--frames", "2", "--path", "orbit", "--video", str(video),
                *extra])


VIDEO_OUTS = [  # (id, how the --video path is made, needles)
    ("users-file", "mine.mp4", ("--video", "mine.mp4", "not written by")),
    ("a-folder", "dir.mp4/", ("--video", "dir.mp4", "is a folder", "name the file")),
    ("under-a-file", "notes.txt/v.mp4", ("--video", "notes.txt is a file, not a folder")),
]


@pytest.mark.parametrize("case,name,needles", VIDEO_OUTS, ids=[c[0] for c in VIDEO_OUTS])
def test_a_video_path_it_cannot_write_is_refused_naming_video(scene, tmp_path, case, name, needles):
    (tmp_path / "mine.mp4").write_bytes(b"the user's own")
    (tmp_path / "dir.mp4").mkdir()
    (tmp_path / "notes.txt").write_text("notes")
    before = _listing(tmp_path)
    line = refused(_video(scene, tmp_path / name.rstrip("/")), *needles)
    assert "--out" not in line, line
    assert _listing(tmp_path) == before and (tmp_path / "mine.mp4").read_bytes() == b"the user's own"


def test_an_export_under_a_file_is_refused(scene, tmp_path):
    (tmp_path / "notes.txt").write_text("notes")
    refused(run(["-m", "splat_train", "export", "--format", "splat", "--out", str(tmp_path / "notes.txt" / "m.splat"),
                 str(scene["model"])]), "--out", "notes.txt is a file, not a folder")
    assert _listing(tmp_path) == {"notes.txt"}


FOLDER_AS_PLY = [  # (id, argv with @dir for the folder given as a PLY file)
    ("render-model", ["-m", "splat_train", "render", "--model", "@dir", "--cameras", "@cams", "--width", "32",
                      "--height", "24", "--out", "@out"]),
    ("train-seed-ply", ["-m", "splat_train", "--seed-ply", "@dir", "--cameras", "@scene/sparse/0", "--images",
                        "@scene/images", "--iterations", "1", "--out", "@out"]),
    ("floaters-model", ["-m", "evaluation", "floaters", "--model", "seed=@dir", "--align", "@afile", "--scene",
                        "@scene", "--out", "@out/f.json"]),
]


@pytest.mark.parametrize("case,argv", FOLDER_AS_PLY, ids=[c[0] for c in FOLDER_AS_PLY])
def test_a_folder_given_for_a_ply_is_named_as_a_folder(scene, tmp_path, case, argv):
    (tmp_path / "dir").mkdir()
    write_gaussian_ply(tmp_path / "dir" / "model.ply", make_model(5))
    if case == "floaters-model":  # the model is read after the alignment
        (tmp_path / "align.json").write_text(json.dumps({"scale": 1.0, "R": np.eye(3).tolist(), "t": [0, 0, 0]}))
    args = [a.replace("@dir", str(tmp_path / "dir")).replace("@cams", str(scene["cams"]))
            .replace("@scene", str(scene["scene"])).replace("@out", str(tmp_path / "out"))
            .replace("@afile", str(tmp_path / "align.json")) for a in argv]
    refused(run(args), "PLY file", "dir is a folder, not a file", "model.ply")
    assert not (tmp_path / "out").exists()


FILE_AS_FOLDER = [  # (id, argv with @afile where a folder belongs, needles)
    ("split-scene", ["-m", "camio", "split", "--scene", "@afile", "--n", "3", "--out", "@out/s.json"],
     ("afile is a file, not a folder",)),
    ("vggt-images", ["-m", "vggt_init", "--images", "@afile", "--out", "@out"], ("afile is a file, not a folder",)),
    ("tables-results", ["-m", "evaluation", "tables", "--results", "@afile", "--out", "@out"],
     ("results folder", "afile is a file, not a folder")),
    ("convert-images-subdir", ["-m", "camio", "convert", "--src", "@scene", "--images-subdir", "@afile", "--out",
                               "@out"], ("image folder", "afile is a file, not a folder")),
    ("images-pred", ["-m", "evaluation", "images", "--pred", "@afile", "--gt", "@scene/images", "--out", "@out/m.json"],
     ("image folder", "afile is a file, not a folder")),
    ("report-results", ["-m", "evaluation", "report", "--results", "@afile", "--out", "@out"],
     ("results folder", "afile is a file, not a folder")),
    ("plots-results", ["-m", "evaluation", "plots", "--results", "@afile", "--out", "@out"],
     ("results folder", "afile is a file, not a folder")),
]


@pytest.mark.parametrize("case,argv,needles", FILE_AS_FOLDER, ids=[c[0] for c in FILE_AS_FOLDER])
def test_a_file_given_for_a_folder_is_named_as_a_file(scene, tmp_path, case, argv, needles):
    args = [a.replace("@afile", str(scene["afile"])).replace("@scene", str(scene["scene"]))
            .replace("@out", str(tmp_path / "out")) for a in argv]
    refused(run(args), *needles)
    assert not (tmp_path / "out").exists()


# -- array headers that claim more than the file holds ------------------------------------------

def _npz(path, members: dict[str, bytes]) -> str:
    with zipfile.ZipFile(path, "w") as z:
        for k, v in members.items():
            z.writestr(k + ".npy", v)
    return str(path)


def test_predictions_whose_header_claims_terabytes_are_refused_before_allocating(scene, tmp_path):
    """A predictions.npz whose world_points header claims 10^12 values (a MemoryError traceback
    asking for 10.9 TiB): refused from the header, in one line naming the file and the member,
    under a 2 GB address-space limit, so nothing of the claimed size was asked for."""
    huge = _npz(tmp_path / "huge.npz", {"world_points": _npy_header((10 ** 6, 10 ** 3, 10 ** 3, 3)),
                                        "extrinsic": _npy_header((10 ** 6, 3, 4))})
    proc = subprocess.run(["bash", "-c", 'ulimit -v 2000000 && exec "$@"', "-", sys.executable, "-m", "bridge",
                           "--pred", huge, "--out", str(tmp_path / "out")], capture_output=True, text=True,
                          cwd=ROOT, env=ENV, timeout=120)
    refused(proc, "huge.npz", "the header claims an array of shape", "write it again")
    assert not (tmp_path / "out").exists()


def test_predictions_holding_a_pickle_are_refused(scene, tmp_path):
    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    bad = _npz(tmp_path / "p.npz", {"world_points": buf.getvalue()})
    refused(run(["-m", "bridge", "--pred", bad, "--out", str(tmp_path / "out")]), "p.npz", "Python objects")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("case", ["huge-header", "not-npy", "nex-intrinsics-not-npy"])
def test_llff_poses_that_are_no_readable_array_are_refused(scene, tmp_path, case):
    """poses_bounds.npy whose header claims 10^11 rows (numpy tried to allocate 13 TB), text
    named .npy, and NeX's hwf_cxcy.npy as text: one line naming the file."""
    src = tmp_path / "llff"
    (src / "images").mkdir(parents=True)
    for name in sorted(os.listdir(scene["scene"] / "images"))[:3]:
        (src / "images" / name).write_bytes((scene["scene"] / "images" / name).read_bytes())
    if case == "huge-header":
        (src / "poses_bounds.npy").write_bytes(_npy_header((10 ** 11, 17), "<f8"))
        needles = ("poses_bounds.npy", "header claims", "[100000000000, 17]")
    elif case == "not-npy":
        (src / "poses_bounds.npy").write_text("garbage")
        needles = ("poses_bounds.npy", "not a readable")
    else:
        np.save(src / "poses_bounds.npy", np.zeros((3, 14)))
        (src / "hwf_cxcy.npy").write_text("garbage")
        needles = ("hwf_cxcy.npy", "not a readable")
    refused(run(["-m", "camio", "convert", "--src", str(src), "--out", str(tmp_path / "out")]), *needles)
    assert not (tmp_path / "out").exists()


def test_a_ply_whose_header_claims_a_trillion_vertices_is_refused(scene, tmp_path):
    head = "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n"
    head += "".join(f"property float {x}\n" for x in "xyz") + "end_header\n"
    (tmp_path / "huge.ply").write_bytes(head.encode() + b"\0" * 120)
    refused(run(["-m", "splat_train", "export", "--format", "splat", "--out", str(tmp_path / "o.splat"),
                 str(tmp_path / "huge.ply")]), "huge.ply", "truncated", "1000000000000 vertices")
    assert not (tmp_path / "o.splat").exists()


@pytest.mark.parametrize("content", [b"", b"ply\nformat binary_little_endian 1.0\nelem"], ids=["empty", "cut-header"])
def test_an_empty_or_cut_ply_is_refused(scene, tmp_path, content):
    (tmp_path / "m.ply").write_bytes(content)
    refused(run(["-m", "splat_train", "export", "--format", "splat", "--out", str(tmp_path / "o.splat"),
                 str(tmp_path / "m.ply")]), "m.ply", "not a PLY file")
    assert not (tmp_path / "o.splat").exists()


# -- JSON and name lists -------------------------------------------------------------------------

@pytest.mark.parametrize("case,text,needles", [
    ("not-json", "hi\n", ("align.json", "is not an align.json", "python -m evaluation align")),
    ("nan-scale", '{"scale": NaN, "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,0]}', ("align.json", "finite")),
    ("r-not-3x3", '{"scale": 1, "R": [1, 0, 0], "t": [0,0,0]}', ("align.json", "R 3x3")),
], ids=["not-json", "nan-scale", "r-not-3x3"])
def test_floaters_refuse_an_alignment_it_cannot_use(scene, tmp_path, case, text, needles):
    (tmp_path / "align.json").write_text(text)
    refused(run(["-m", "evaluation", "floaters", "--model", f"seed={scene['model']}", "--align",
                 str(tmp_path / "align.json"), "--scene", str(scene["scene"]), "--out", str(tmp_path / "f.json")]),
            *needles)
    assert not (tmp_path / "f.json").exists()


@pytest.mark.parametrize("command", ["pose", "align"])
@pytest.mark.parametrize("content", ["", "# only a comment\n\n"], ids=["empty", "comment-only"])
def test_a_names_list_that_names_nothing_is_refused(scene, tmp_path, command, content):
    """pose wrote a pose.json of 0 matched views (exit 0); align blamed the models."""
    (tmp_path / "names.txt").write_text(content)
    model = str(scene["scene"] / "sparse" / "0")
    flag = "--names" if command == "pose" else "--train-names"
    refused(run(["-m", "evaluation", command, "--pred", model, "--ref", model, flag, str(tmp_path / "names.txt"),
                 "--out", str(tmp_path / "o.json")]), "names.txt names no image")
    assert not (tmp_path / "o.json").exists()


def test_study_cells_that_are_not_json_are_refused_naming_the_flag(scene, tmp_path):
    refused(run(["-m", "evaluation", "study", "--results", str(scene["empty"]), "--cells", '{"a":',
                 "--out", str(tmp_path / "st")]), "--cells", "is not JSON")
    assert not (tmp_path / "st").exists()


# -- odd but legitimate names --------------------------------------------------------------------

def test_an_out_with_a_line_break_in_its_name_works(tmp_path):
    out = tmp_path / "new\nline dir"
    p = run(["-m", "camio", "synth", "--out", str(out), "--views", "4", "--width", "32", "-q"])
    assert p.returncode == 0, p.stderr
    assert (out / "split.json").is_file() and (out / ".stage").read_text().startswith("camio synth")


def test_a_split_into_a_folder_named_with_unicode_and_quotes_works(scene, tmp_path):
    out = tmp_path / "ünï cødé \"q\" 's" / "split.json"
    p = run(["-m", "camio", "split", "--scene", str(scene["scene"]), "--n", "3", "--out", str(out)])
    assert p.returncode == 0, p.stderr
    assert json.loads(out.read_text())["train"]["3"]


def test_inputs_given_through_symbolic_links_are_read(scene, tmp_path):
    """A model folder and a scene folder given as links: read as their targets (only an output
    may not be a link)."""
    (tmp_path / "model").symlink_to(scene["scene"] / "sparse" / "0")
    (tmp_path / "scene").symlink_to(scene["scene"])
    p = run(["-m", "evaluation", "pose", "--pred", str(tmp_path / "model"), "--ref", str(tmp_path / "model"),
             "--out", str(tmp_path / "pose.json")])
    assert p.returncode == 0 and json.loads((tmp_path / "pose.json").read_text())["n_matched"] == 6, p.stderr
    p = run(["-m", "camio", "convert", "--src", str(tmp_path / "scene"), "--out", str(tmp_path / "conv")])
    assert p.returncode == 0 and len(os.listdir(tmp_path / "conv" / "images")) == 6, p.stderr


FOLDER_AS_FILE = [  # (id, argv with @dir where a file belongs, needles)
    ("bridge-pred", ["-m", "bridge", "--pred", "@dir", "--out", "@out"],
     ("predictions file", "is a folder, not a file", "vggt_init")),
    ("pose-names", ["-m", "evaluation", "pose", "--pred", "@model", "--ref", "@model", "--names", "@dir", "--out",
                    "@out/p.json"], ("names file", "is a folder, not a file")),
    ("vggt-image-list", ["-m", "vggt_init", "--images", "@scene/images", "--image-list", "@dir", "--out", "@out"],
     ("image list", "is a folder, not a file")),
    ("split-manifest", ["-m", "camio", "split", "--scene", "@scene", "--n", "3", "--manifest", "@dir", "--out",
                        "@out/s.json"], ("split manifest", "is a folder, not a file")),
]


@pytest.mark.parametrize("case,argv,needles", FOLDER_AS_FILE, ids=[c[0] for c in FOLDER_AS_FILE])
def test_a_folder_given_for_a_file_is_named_as_a_folder(scene, tmp_path, case, argv, needles):
    """bridge said `predictions file DIR does not exist`, pose `names file DIR does not exist`,
    vggt_init raised a bare `IsADirectoryError` traceback."""
    args = [a.replace("@dir", str(scene["empty"])).replace("@model", str(scene["scene"] / "sparse" / "0"))
            .replace("@scene", str(scene["scene"])).replace("@out", str(tmp_path / "out")) for a in argv]
    refused(run(args), *needles)
    assert not (tmp_path / "out").exists()


def test_a_names_list_that_is_not_text_is_refused(scene, tmp_path):
    (tmp_path / "names.txt").write_bytes(b"ab\xff\xfe\x00\x81cd\n")
    model = str(scene["scene"] / "sparse" / "0")
    refused(run(["-m", "evaluation", "align", "--pred", model, "--ref", model, "--train-names",
                 str(tmp_path / "names.txt"), "--out", str(tmp_path / "a.json")]), "names.txt", "not a text file")
    assert not (tmp_path / "a.json").exists()


def test_a_depth_prior_whose_header_claims_terabytes_is_refused(scene, tmp_path):
    huge = _npz(tmp_path / "prior.npz", {"z": _npy_header((10 ** 12,)), "xy": _npy_header((10 ** 12, 2))})
    refused(run(["-m", "splat_train", "--seed-ply", str(scene["model"]), "--cameras", str(scene["scene"] / "sparse" / "0"),
                 "--images", str(scene["scene"] / "images"), "--depth-prior", huge, "--iterations", "1",
                 "--out", str(tmp_path / "out")]), "prior.npz", "header claims", "write it again")
    assert not (tmp_path / "out").exists()


def test_a_split_manifest_that_is_not_json_is_refused(scene, tmp_path):
    (tmp_path / "m.json").write_bytes(b"\xff\xfe not json")
    refused(run(["-m", "camio", "split", "--scene", str(scene["scene"]), "--n", "3", "--manifest",
                 str(tmp_path / "m.json"), "--out", str(tmp_path / "s.json")]), "split manifest", "m.json",
            "give a JSON object")
    assert not (tmp_path / "s.json").exists()


# -- a snakemake run killed outright ---------------------------------------------------------------

def _children(pid: int) -> list[int]:
    kids = []
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as f:
            kids += [int(x) for x in f.read().split()]
    return kids


def test_photos_after_snakemake_was_killed_names_the_stale_lock_and_unlocks_it(tmp_path):
    """While the run goes on, a second command on the folder (even with --unlock) is refused
    naming snakemake's pid. SIGKILL of snakemake (and of the script) leaves its lock; the rerun
    said `LockException` / `Directory cannot be locked` from inside snakemake. Now: exit 2, one
    line naming the lock and `--unlock`, nothing run; `--unlock` removes only that run's lock
    files and the run goes on."""
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    from camio.images import write_image

    for i in range(3):
        write_image(photos / f"p{i}.png", rng.uniform(size=(48, 64, 3)).astype(np.float32))
    out = tmp_path / "out"
    locks = ROOT / ".snakemake" / "locks"
    proc = subprocess.Popen([sys.executable, "scripts/photos.py", str(photos), "--out", str(out), "--init", "colmap",
                             "--cores", "1"], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 90
        held = []
        while time.monotonic() < deadline and not held:
            time.sleep(0.2)
            held = [p for p in locks.glob("*.lock") if str(out) in p.read_text(errors="replace")] \
                if locks.is_dir() else []
        assert held, "snakemake never locked the folder"
        kids = _children(proc.pid)
        alive = run(["scripts/photos.py", str(photos), "--out", str(out), "-n", "--unlock"])  # while it runs
        line = refused(alive, "is being run by snakemake (pid ")
        assert os.path.exists(f"/proc/{line.split('(pid ')[1].split(',')[0]}"), line  # a live process
        assert all(p.exists() for p in held)
        for kid in kids:
            os.killpg(kid, signal.SIGKILL)  # snakemake and its jobs (a session of their own)
        proc.kill()
        proc.wait()
        left = {p: p.read_text() for p in held}  # what SIGKILL leaves behind
        before = _listing(out)
        for p, text in left.items():  # put back if another test's snakemake, ending, cleared the lock folder
            if not p.exists():
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_text(text)
        line = refused(run(["scripts/photos.py", str(photos), "--out", str(out), "-n"]), "locked", "no longer running",
                       "--unlock")
        assert str(out) in line and _listing(out) == before
        p = run(["scripts/photos.py", str(photos), "--out", str(out), "-n", "--unlock"], timeout=300)
        assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
        assert "removed" in p.stdout and not any(p.exists() for p in held)
    finally:
        proc.kill()
        for p in locks.glob("*.lock") if locks.is_dir() else []:
            if str(out) in p.read_text(errors="replace"):
                p.unlink(missing_ok=True)


# -- the install script on a machine that already has torch ---------------------------------------

@pytest.mark.parametrize("case,version,isolated,rc,needles", [
    ("torch-at-the-pin", None, False, 0, ("is the pin: kept", "constraints/cpu.txt -e .[dev]")),
    ("a-cuda-build-of-another-version", "2.5.1+cu124", False, 0,
     ("keeping the machine's torch 2.5.1+cu124", "not installed over it", "without torch")),
    ("older-than-the-range", "2.3.0", False, 2, ("torch 2.3.0", "older than the project's torch>=2.4", "without SYSTEM_SITE_PACKAGES=1")),
    ("isolated-venv", "2.5.1+cu124", True, 0, ("would create", "(isolated)", "pip install -c constraints/cpu.txt torch==")),
    ("the-default", "2.5.1+cu124", None, 0, ("would create", "(isolated)", "pip install -c constraints/cpu.txt torch==")),
], ids=["torch-at-the-pin", "a-cuda-build-of-another-version", "older-than-the-range", "isolated-venv", "the-default"])
def test_install_dry_run_keeps_or_refuses_the_machines_torch(tmp_path, case, version, isolated, rc, needles):
    """`DRY_RUN=1 bash scripts/install.sh` for a new venv. Made with SYSTEM_SITE_PACKAGES=1, the
    machine's torch (this interpreter's, or a package named torch with that version first on
    PYTHONPATH, standing for another build) is kept, or refused when older than pyproject's
    range; an isolated venv, the default, ignores it and gets the pin; nothing is created."""
    env = {k: v for k, v in os.environ.items() if k != "SYSTEM_SITE_PACKAGES"}
    env.update({"DRY_RUN": "1", "VENV": str(tmp_path / "venv"), "PYTHON": sys.executable})
    if isolated is not None:
        env["SYSTEM_SITE_PACKAGES"] = "0" if isolated else "1"
    if version:
        (tmp_path / "site" / "torch").mkdir(parents=True)
        (tmp_path / "site" / "torch" / "__init__.py").write_text(f"__version__ = {version!r}\n")
        env["PYTHONPATH"] = str(tmp_path / "site")
    p = subprocess.run(["bash", "scripts/install.sh"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    text = p.stdout + p.stderr
    assert p.returncode == rc, text
    for n in needles:
        assert n in text, (n, text)
    assert not (tmp_path / "venv").exists() and "Traceback" not in text


def test_a_depth_prior_with_non_finite_samples_is_refused(scene, tmp_path):
    """A NaN depth and an infinite weight were accepted and trained on (exit 0); now refused when
    the file is read, naming how many samples of each field are not finite."""
    from camio.depth_prior import DEPTH_PRIOR_FILE

    names = sorted(os.listdir(scene["scene"] / "images"))
    z = np.ones(4, np.float32)
    z[1] = np.nan
    weight = np.ones(4, np.float32)
    weight[2] = np.inf
    np.savez(tmp_path / DEPTH_PRIOR_FILE, image_names=np.asarray(names), image_sizes=np.full((len(names), 2), 48),
             view=np.zeros(4, np.int64), xy=np.full((4, 2), 10.0, np.float32), z=z, weight=weight,
             source=np.asarray("sparse"))
    refused(run(["-m", "splat_train", "--seed-ply", str(scene["model"]), "--cameras", str(scene["scene"] / "sparse" / "0"),
                 "--images", str(scene["scene"] / "images"), "--depth-prior", str(tmp_path / DEPTH_PRIOR_FILE),
                 "--iterations", "1", "--out", str(tmp_path / "out")]), DEPTH_PRIOR_FILE, "non-finite", "z: 1",
            "weight: 1")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["tables", "plots", "report"])
@pytest.mark.parametrize("tree", ["empty", "unrelated"])
def test_a_results_folder_without_runs_is_refused_and_nothing_is_written(tmp_path, command, tree):
    """A wrong --results (an empty folder, or one of photos) gave empty tables and exit 0."""
    results = tmp_path / "res"
    results.mkdir()
    if tree == "unrelated":
        (results / "photos").mkdir()
        (results / "photos" / "a.jpg").write_bytes(b"\xff\xd8")
    before = _listing(tmp_path)
    p = run(["-m", "evaluation", command, "--results", str(results), "--out", str(tmp_path / "out")])
    refused(p, str(results), "no run found")
    assert _listing(tmp_path) == before


def test_install_names_an_existing_venv_that_sees_the_system_and_keeps_it(tmp_path):
    """A .venv made by an older install with --system-site-packages is not removed behind the
    user's back (VENV may be their own): one line says how to get the isolated default."""
    venv = tmp_path / "venv"
    venv.mkdir()
    (venv / "pyvenv.cfg").write_text("home = /usr/bin\ninclude-system-site-packages = true\n")
    env = {k: v for k, v in os.environ.items() if k != "SYSTEM_SITE_PACKAGES"}
    env.update({"DRY_RUN": "1", "VENV": str(venv), "PYTHON": sys.executable})
    p = subprocess.run(["bash", "scripts/install.sh"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    assert f"{venv} was made with --system-site-packages and is kept" in p.stdout
    assert (venv / "pyvenv.cfg").read_text().endswith("= true\n") and sorted(os.listdir(venv)) == ["pyvenv.cfg"]
