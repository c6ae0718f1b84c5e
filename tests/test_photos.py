"""Your own photos in one command (scripts/photos.py): a folder of a few small photos becomes
cameras, a seed, a trained model, a render of every photo and the command that views it,
through the real Snakemake workflow; VGGT is the weight-compatible test model
(tests/data/vggt/shared). Without weights the run says so and plans COLMAP alone."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

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
