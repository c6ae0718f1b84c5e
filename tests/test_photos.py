"""Your own photos in one command (scripts/photos.py): a folder of a few small photos becomes
cameras, a seed, a trained model, a render of every photo and the command that views it,
through the real Snakemake workflow; VGGT is the weight-compatible test model
(tests/data/vggt/shared). Without weights the run says so and plans COLMAP alone."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from _cli import refused

REPO = Path(__file__).resolve().parents[1]
FIXTURE = REPO / "tests" / "data" / "vggt" / "shared"
N_PHOTOS = 4


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """A folder of N_PHOTOS small photographs and nothing else (no cameras)."""
    scene = tmp_path_factory.mktemp("synth") / "scene"
    subprocess.run([sys.executable, "-m", "camio", "-q", "synth", "--out", str(scene), "--views", str(N_PHOTOS + 1),
                    "--width", "64", "--seed", "0"], check=True, capture_output=True)
    folder = tmp_path_factory.mktemp("mine") / "garden"
    folder.mkdir()
    for p in sorted((scene / "images").iterdir())[:N_PHOTOS]:
        shutil.copy(p, folder / p.name)
    return folder


def _env(tmp_path: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("VGGT_CHECKPOINT", "HF_HUB_CACHE", "HF_HOME")}
    env.update(HF_HUB_OFFLINE="1", HF_HOME=str(tmp_path / "hf"),
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    return env


def _photos(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "scripts" / "photos.py"), *args], capture_output=True,
                          text=True, timeout=900, env=_env(tmp_path), cwd=tmp_path)


def test_bad_folder_is_one_line(tmp_path):
    proc = _photos(tmp_path, str(tmp_path / "nothing"))
    assert proc.returncode == 2 and proc.stderr.startswith("scripts/photos.py: error:"), proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_without_weights_says_so_and_plans_colmap_alone(tmp_path, photos):
    proc = _photos(tmp_path, str(photos), "--out", str(tmp_path / "out"), "-n")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    assert sum(ln.startswith("VGGT skipped:") for ln in out.splitlines()) == 1, out[-4000:]
    assert "rule colmap_baseline:" in out and "rule vggt_init:" not in out
    cfg = yaml.safe_load((tmp_path / "out" / "config.yaml").read_text())
    scene = cfg["datasets"]["photos"]["scenes"]["garden"]
    assert scene["views"] == [N_PHOTOS] and scene["reference"] is False
    split = json.loads((tmp_path / "out" / "split.json").read_text())
    assert split["test"] == [] and len(split["train"][str(N_PHOTOS)]) == N_PHOTOS


def test_a_photo_run_writes_snapshots_and_says_how_to_watch_them(tmp_path, photos):
    """photos.py sets train.snapshot_every on its first run (the workflow then passes it to the
    trainer: tests/test_workflow_dryrun.py) and prints the viewer command that follows each
    run's training live, before the workflow starts."""
    out = tmp_path / "out"
    proc = _photos(tmp_path, str(photos), "--out", str(out), "--init", "colmap", "-n")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    every = cfg["train"]["snapshot_every"]
    assert every >= 1 and f"the model every {every} iterations" in proc.stdout
    run = out / "photos" / "garden" / f"n{N_PHOTOS}" / "colmap" / "uniform" / "train"
    assert f"[photos]   python -m splat_train view --model {run}" in proc.stdout
    # the user turns snapshots off: no flag, no viewer line
    cfg["train"]["snapshot_every"] = None
    head = (out / "config.yaml").read_text().splitlines()[0]
    (out / "config.yaml").write_text(f"{head}\n{yaml.safe_dump(cfg, sort_keys=False)}")
    proc = _photos(tmp_path, str(photos), "--out", str(out), "-n")
    assert proc.returncode == 0 and "splat_train view" not in proc.stdout, proc.stdout[-2000:]


def test_rerun_keeps_the_users_config_edits(tmp_path, photos):
    """config.yaml is the user's to edit: a rerun writes the folder's keys and those of the flags
    given, and keeps every other key; a rerun that changes nothing leaves the file as it is. The
    working resolution (--max-size) is a key of the scene, which camio convert receives."""
    out, cfg_path = tmp_path / "out", tmp_path / "out" / "config.yaml"
    first = _photos(tmp_path, str(photos), "--out", str(out), "--max-size", "48", "-n", "--", "-p")
    assert first.returncode == 0, (first.stdout + first.stderr)[-4000:]
    assert f"[photos] {N_PHOTOS} photos 64x48 -> 48x36 working resolution" in first.stdout
    assert "--format folder --max-size 48 --out" in first.stdout  # the workflow converts at that size
    cfg = yaml.safe_load(cfg_path.read_text())
    scene = cfg["datasets"]["photos"]["scenes"]["garden"]
    assert scene["max_size"] == 48 and cfg["initialisers"] == ["vggt", "colmap"]

    cfg["initialisers"], cfg["train"], scene["allow_mixed"] = ["colmap"], {"recipe": "paper"}, True
    head = cfg_path.read_text().splitlines()[0]
    cfg_path.write_text(f"{head}\n# my edits\n{yaml.safe_dump(cfg, sort_keys=False)}")
    second = _photos(tmp_path, str(photos), "--out", str(out), "--iterations", "5", "-n")
    assert second.returncode == 0, (second.stdout + second.stderr)[-4000:]
    assert "initialiser(s): colmap" in second.stdout and "64x48 -> 48x36 working resolution" in second.stdout
    cfg = yaml.safe_load(cfg_path.read_text())
    scene = cfg["datasets"]["photos"]["scenes"]["garden"]
    assert cfg["initialisers"] == ["colmap"] and cfg["train"] == {"recipe": "paper", "iterations": 5, "eval_every": 5}
    assert scene["allow_mixed"] is True and scene["max_size"] == 48 and scene["views"] == [N_PHOTOS]

    text = cfg_path.read_text().replace("\n", "\n# my note\n", 1)
    cfg_path.write_text(text)
    third = _photos(tmp_path, str(photos), "--out", str(out), "--max-size", "0", "--init", "both", "-n")
    assert third.returncode == 0 and "64x48 -> 64x48 working resolution (full resolution)" in third.stdout
    cfg = yaml.safe_load(cfg_path.read_text())
    assert cfg["datasets"]["photos"]["scenes"]["garden"]["max_size"] == 0 and cfg["initialisers"] == ["vggt", "colmap"]
    assert cfg["train"]["recipe"] == "paper"
    text = cfg_path.read_text()
    assert _photos(tmp_path, str(photos), "--out", str(out), "-n").returncode == 0
    assert cfg_path.read_text() == text  # nothing to write: left as it is


def test_a_config_it_did_not_write_is_refused(tmp_path, photos):
    """A config.yaml in --out that photos.py did not write, or wrote for another folder, is left
    alone: exit 2, one line saying how to go on."""
    out = tmp_path / "out"
    out.mkdir()
    mine = "datasets: {}\nviews: [3]\ninitialisers: [colmap]\n"
    (out / "config.yaml").write_text(mine)
    proc = _photos(tmp_path, str(photos), "--out", str(out), "-n")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "not written by scripts/photos.py" in proc.stderr and "choose another --out" in proc.stderr
    (out / "config.yaml").write_text(f"# Written by scripts/photos.py for {tmp_path / 'elsewhere'}\n{mine}")
    proc = _photos(tmp_path, str(photos), "--out", str(out), "-n")
    assert proc.returncode == 2 and "written for another folder" in proc.stderr, proc.stderr
    assert (out / "config.yaml").read_text().endswith(mine) and sorted(p.name for p in out.iterdir()) == ["config.yaml"]


@pytest.mark.slow
@pytest.mark.skipif(not (FIXTURE / "weights.safetensors").is_file(), reason="VGGT fixture missing")
def test_photo_folder_to_a_viewable_model(tmp_path, photos):
    out = tmp_path / "out"
    args = [str(photos), "--out", str(out), "--init", "vggt", "--iterations", "3",
            "--vggt-checkpoint", str(FIXTURE / "weights.safetensors"),
            "--vggt-model-config", str(FIXTURE / "config.json"), "--vggt-image-size", "56"]
    proc = _photos(tmp_path, *args)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-6000:]

    run = out / "photos" / "garden" / f"n{N_PHOTOS}" / "vggt"
    assert (run / "sparse" / "0").is_dir()
    mode = run / "gated"
    assert (mode / "bridge" / "seed.ply").is_file() and (mode / "train" / "model.ply").is_file()
    renders = sorted(p.stem for p in (mode / "train_renders").glob("*.png"))
    assert renders == sorted(p.stem for p in photos.iterdir())
    assert (out / "report" / "index.html").is_file()

    summary = (out / "photos.md").read_text()
    assert summary in proc.stdout
    view = [ln.strip() for ln in summary.splitlines() if "splat_train view" in ln]
    assert len(view) == 1
    argv = shlex.split(view[0])
    assert argv[:4] == ["python", "-m", "splat_train", "view"]
    from splat_train.view.cli import parser

    parsed = parser().parse_args(argv[4:])
    for path in (parsed.model, parsed.cameras, parsed.seed_ply):
        assert Path(path).exists(), path

    again = _photos(tmp_path, *args)  # the same command again resumes: nothing to do
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr


@pytest.mark.slow
def test_dense_seeds_from_multi_view_stereo_on_colmaps_cameras(tmp_path):
    """``--dense``: COLMAP's cameras of the photos, then multi-view stereo of the photos on them
    (colmap_mvs), its dense points seeded with Eq. 2's opacity, trained and rendered."""
    scene = tmp_path / "synth"
    subprocess.run([sys.executable, "-m", "camio", "-q", "synth", "--out", str(scene), "--views", "16",
                    "--width", "256", "--seed", "0"], check=True, capture_output=True)
    folder = tmp_path / "yard"
    folder.mkdir()
    for p in sorted((scene / "images").iterdir())[::3]:  # 6 photos along the arc
        shutil.copy(p, folder / p.name)
    out = tmp_path / "out"
    proc = _photos(tmp_path, str(folder), "--out", str(out), "--init", "colmap", "--dense", "--iterations", "3")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-6000:]
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["initialisers"] == ["colmap", "colmap_mvs"]
    run = out / "photos" / "yard" / "n6" / "colmap_mvs"
    status = json.loads((run / "status.json").read_text())
    assert status["cameras_source"].endswith("colmap/sparse/0") and status["points"] > 1000
    bridge = json.loads((run / "gated" / "bridge" / "bridge.json").read_text())
    assert bridge["alpha_out"]["max"] > bridge["alpha_out"]["min"]  # the confidence sets the opacity
    assert len(list((run / "gated" / "train_renders").glob("*.png"))) == 6
    assert "### colmap_mvs: ran" in (out / "photos.md").read_text()


# ------------------------------------------------------------------ photos as people take them
def _write_oriented(path: Path, upright: "np.ndarray", orientation: int) -> None:
    """Write ``upright`` [H, W, 3] uint8 as a JPEG that stores it on its side with an EXIF
    Orientation tag (6: the viewer turns the stored pixels 90 degrees clockwise), through
    OpenImageIO directly, as a phone held upright writes it."""
    import numpy as np
    import OpenImageIO as oiio

    stored = {1: upright, 6: np.rot90(upright, k=1)}[orientation]
    h, w, c = stored.shape
    spec = oiio.ImageSpec(w, h, c, "uint8")
    spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(stored))
    out.close()


@pytest.fixture(scope="module")
def mixed(tmp_path_factory) -> Path:
    """Six photos along an arc, landscape 320x240 and portrait 180x240 in turn; each portrait
    one is stored sideways (240x180 pixels) with EXIF Orientation 6."""
    from camio.images import read_image_uint8

    scene = tmp_path_factory.mktemp("synth") / "scene"
    subprocess.run([sys.executable, "-m", "camio", "-q", "synth", "--out", str(scene), "--views", "12",
                    "--width", "320", "--seed", "0"], check=True, capture_output=True)
    folder = tmp_path_factory.mktemp("mixed") / "street"
    folder.mkdir()
    for k, p in enumerate(sorted((scene / "images").iterdir())[::2]):
        img = read_image_uint8(p)
        if k % 2:  # portrait: the middle 3/4 of the height's width, a phone turned upright
            x0 = (img.shape[1] - 180) // 2
            _write_oriented(folder / f"{p.stem}.jpg", img[:, x0:x0 + 180], 6)
        else:
            _write_oriented(folder / f"{p.stem}.jpg", img, 1)
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("sigint", ["default", "ignored"])
def test_mixed_orientation_photos_run_end_to_end_and_resume_after_sigterm(tmp_path, mixed, sigint):
    """Portrait and landscape photos, the portrait ones EXIF-rotated, in one folder: the run says
    which it turned upright, COLMAP gives each size its own camera, and every photo is trained
    on and rendered at its own upright size. A SIGTERM in the middle stops the run (the signal
    forwarded to snakemake, one line, exit 128 + 15); the same command then resumes to the end.
    Also where the command starts with SIGINT ignored (a background job of a script): snakemake,
    which the command stops with SIGINT, used to inherit the ignore and ran on to the end."""
    import numpy as np

    from camio.colmap import read_model
    from camio.images import image_size, read_image

    out = tmp_path / "out"
    args = [sys.executable, str(REPO / "scripts" / "photos.py"), str(mixed), "--out", str(out), "--init", "colmap",
            "--iterations", "3"]
    disposition = signal.SIG_DFL if sigint == "default" else signal.SIG_IGN
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(tmp_path),
                            cwd=tmp_path, preexec_fn=lambda: signal.signal(signal.SIGINT, disposition))
    seen = []
    for line in proc.stdout:  # stop once the conversion is done and later jobs run
        seen.append(line)
        if "(convert_scene)" in line:
            proc.send_signal(signal.SIGTERM)
            break
    rest, err = proc.communicate(timeout=120)
    text = "".join(seen) + rest
    assert proc.returncode == 128 + signal.SIGTERM, text + err
    assert err.strip().splitlines() == [err.strip()] and "stopped by SIGTERM" in err and "resumes" in err, err
    assert "EXIF orientation applied: 3 of 6 image(s) turned upright" in text
    assert "6 photos of 2 sizes (3 x 180x240 -> 180x240, 3 x 320x240 -> 320x240)" in text
    assert "localrule" not in text and "jobid" not in text  # snakemake's job blocks only with -v
    assert not (out / "photos.md").exists()

    again = _photos(tmp_path, *args[2:])
    assert again.returncode == 0, (again.stdout + again.stderr)[-6000:]
    assert "(colmap_baseline)" in again.stdout and "(convert_scene)" not in again.stdout  # resumed

    scene = out / "photos" / "street"
    for name in ("0002.jpg", "0006.jpg"):  # turned upright when prepared, no tag left
        upright = read_image(scene / "converted" / "images" / name)
        assert upright.shape == (240, 180, 3)
        src = read_image(mixed / name)  # the reader turns it upright too: the same pixels, re-encoded
        assert np.abs(upright - src).mean() < 0.02
    model = read_model(scene / "n6" / "colmap" / "sparse" / "0")
    sizes = {c.name: (c.width, c.height) for c in model.cameras}
    assert len(sizes) == 6 and set(sizes.values()) == {(320, 240), (180, 240)}
    status = json.loads((scene / "n6" / "colmap" / "status.json").read_text())
    assert status["n_cameras"] == 2 and status["registered"] == 6, status
    renders = {p.stem: image_size(p) for p in (scene / "n6" / "colmap" / "uniform" / "train_renders").glob("*.png")}
    assert renders == {Path(n).stem: s for n, s in sizes.items()}
    assert "### colmap: ran, registered 6 of 6 photos" in (out / "photos.md").read_text()


_LOSES_ONE_SIGINT = """
import sys, time

def log(line):  # as snakemake's log handler: a KeyboardInterrupt while it writes is passed over
    try:
        print(line, flush=True)
        time.sleep(2.0)  # a slow write
    except KeyboardInterrupt:
        pass

try:
    log("writing a log line")
    time.sleep(60)  # the next job
except KeyboardInterrupt:
    print("Terminating processes on user request, this might take some time.", flush=True)
    sys.exit(1)
print("ran to the end", flush=True)
"""


def test_a_stop_reaches_snakemake_even_where_it_drops_the_first_sigint(tmp_path):
    """Snakemake (9.27) drops a SIGINT that lands while it writes a log line: its log handler
    passes over a KeyboardInterrupt, and it writes many between two jobs. The run's forwarder
    sends SIGINT again until the child says it is stopping: here a child that drops the first
    one the same way stops within seconds instead of running its next minute-long job to the end."""
    import time

    child = tmp_path / "child.py"
    child.write_text(_LOSES_ONE_SIGINT)
    driver = (f"import json, sys; sys.path[:0] = [{str(REPO / 'scripts')!r}, {str(REPO / 'workflow' / 'scripts')!r}]\n"
              f"import photos\n"
              f"rc, stopped = photos.run_snakemake([sys.executable, {str(child)!r}], __import__('pathlib').Path('.'),"
              f" {{}}, True, False)\n"
              f"print(json.dumps([rc, stopped]))\n")
    proc = subprocess.Popen([sys.executable, "-c", driver], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=_env(tmp_path), cwd=tmp_path)
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if "writing a log line" in line:
            proc.send_signal(signal.SIGTERM)
            sent = time.monotonic()
            break
    rest, err = proc.communicate(timeout=120)
    took = time.monotonic() - sent
    text = "".join(seen) + rest
    assert "ran to the end" not in text, text + err
    assert "on user request" in text and json.loads(text.strip().splitlines()[-1]) == [1, signal.SIGTERM], text + err
    assert took < 30, f"the stop took {took:.1f} s"


@pytest.mark.slow
def test_a_stop_during_training_ends_the_training_within_seconds(tmp_path, mixed):
    """A SIGTERM while a model trains reaches the trainer too (snakemake alone would wait for its
    job to end: an hour on full-size photos): the run ends within seconds, the trainer's log says
    it stopped and kept nothing half-written, and no process of the run is left."""
    import threading
    import time

    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, str(REPO / "scripts" / "photos.py"), str(mixed), "--out", str(out),
                             "--init", "colmap", "--iterations", "1000000"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(tmp_path), cwd=tmp_path)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    log = out / "photos" / "street" / "n6" / "colmap" / "uniform" / "logs" / "train.log"
    try:
        deadline = time.monotonic() + 600
        while not (log.is_file() and "training parts" in log.read_text()):
            assert proc.poll() is None and time.monotonic() < deadline, "".join(lines) + proc.stderr.read()
            time.sleep(0.2)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        proc.wait(timeout=120)
        took = time.monotonic() - sent
        err = proc.stderr.read()
        time.sleep(0.5)
        left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
        shown = subprocess.run(["ps", "-o", "pid,args", "-p", ",".join(left or ["1"])], capture_output=True,
                               text=True).stdout
    finally:  # a stop that did not work leaves no trainer running on
        subprocess.run(["pkill", "-KILL", "-f", str(out)], capture_output=True)
    reader.join(10)
    assert proc.returncode == 128 + signal.SIGTERM and "stopped by SIGTERM" in err, "".join(lines) + err
    assert took < 30, f"the stop took {took:.1f} s"
    assert "stopped by SIGINT" in log.read_text().splitlines()[-1], log.read_text()[-2000:]
    assert not (log.parents[1] / "train" / "model.ply").exists()
    assert not left, shown


def test_dense_on_photos_of_several_sizes_is_refused_up_front(tmp_path, mixed):
    """Multi-view stereo writes one grid for all views: --dense on portrait and landscape photos
    is one line before anything runs, saying what to do."""
    proc = _photos(tmp_path, str(mixed), "--out", str(tmp_path / "out"), "--init", "colmap", "--dense")
    line = refused(proc, "colmap_mvs", "one size", "180x240, 320x240", "without --dense")
    assert line.startswith("scripts/photos.py: error:") and not (tmp_path / "out").exists()


def test_every_unusable_photo_is_named_at_once(tmp_path, photos):
    """A HEIC photo, a truncated JPEG, a tiny PNG and a name with a space: one line names all
    four and why, before anything is written; sidecar files are no photos and pass."""
    from camio.images import read_image, write_image

    folder = tmp_path / "trip"
    shutil.copytree(photos, folder)
    (folder / "IMG_0001.HEIC").write_bytes(b"\x00\x00\x00\x18ftypheic" + bytes(64))
    good = sorted(folder.glob("*.png"))[0]
    cut = folder / "cut.jpg"
    write_image(cut, read_image(good))
    cut.write_bytes(cut.read_bytes()[:400])
    write_image(folder / "tiny.png", read_image(good)[:8, :8])
    shutil.copy(good, folder / "my photo.png")
    (folder / "IMG_0001.xmp").write_text("<x:xmpmeta/>")
    proc = _photos(tmp_path, str(folder), "--out", str(tmp_path / "out"), "-n")
    line = refused(proc, "4 photo(s)", "IMG_0001.HEIC: HEIC is not read here", "cut.jpg: does not decode",
                   "tiny.png: 8x8 px: too small", "my photo.png: the name holds whitespace", "move them out")
    assert "xmp" not in line and not (tmp_path / "out").exists()


@pytest.mark.parametrize("cores", ["0", "-1"])
def test_cores_below_one_is_refused(tmp_path, photos, cores):
    """--cores 0 made snakemake wait for ever: a count below 1 is one line."""
    refused(_photos(tmp_path, str(photos), "--out", str(tmp_path / "out"), "--cores", cores, "-n"),
            "--cores must be at least 1", cores)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("device", ["gpu", "cuda:x", "cuda:-1", "cuda1"])
def test_a_bad_device_is_refused(tmp_path, photos, device):
    refused(_photos(tmp_path, str(photos), "--out", str(tmp_path / "out"), "--device", device, "-n"),
            "--device", repr(device), "cuda:N")


def test_cuda_n_shows_the_jobs_that_gpu_alone(tmp_path, photos):
    """--device cuda:N: VGGT and training are configured for cuda, and the jobs see only GPU N
    (CUDA_VISIBLE_DEVICES), counted among those already visible. Parsing only: no GPU is needed
    for a dry run."""
    env_visible = {**_env(tmp_path), "CUDA_VISIBLE_DEVICES": "3,5"}
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "photos.py"), str(photos), "--out",
                           str(tmp_path / "out"), "--device", "cuda:1", "-n"], capture_output=True, text=True,
                          timeout=600, env=env_visible, cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert "device cuda:1: the jobs see only that GPU (CUDA_VISIBLE_DEVICES=5)" in proc.stdout
    cfg = yaml.safe_load((tmp_path / "out" / "config.yaml").read_text())
    assert cfg["train"]["device"] == "cuda" and cfg["vggt"]["device"] == "cuda"
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "photos.py"), str(photos), "--out",
                           str(tmp_path / "out"), "--device", "cuda:2", "-n"], capture_output=True, text=True,
                          timeout=600, env=env_visible, cwd=tmp_path)
    refused(proc, "--device cuda:2", "CUDA_VISIBLE_DEVICES=3,5", "cuda:0..cuda:1")
