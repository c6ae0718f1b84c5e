"""experiments/sparse_views: the floor (a flat mean-colour image scored like a model), equal
backgrounds, scene-level intervals and covered pixels in the summary."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from experiments.sparse_views import scene_level
from experiments.sparse_views.floor import floor_psnr
from camio.images import write_image

REPO = __import__("pathlib").Path(__file__).resolve().parents[1]


def _rec(scene, recipe, seed, psnr, lpips=0.3, coverage=None, n=3):
    r = {"scene": scene, "role": "evaluation", "n": n, "recipe": recipe, "seed": seed, "iterations": 1000,
         "psnr": psnr, "ssim": 0.5, "lpips_alex": lpips, "lpips_vgg": lpips, "gaussians": 1000,
         "train_s": 1.0, "backend": "cpu", "best_psnr": psnr}
    if coverage is not None:
        r["curve"] = {"iterations": [1000], "psnr": [psnr], "coverage": [coverage], "psnr_covered": [psnr + 1.0]}
    return r


def test_floor_psnr_is_the_flat_mean_colour_image_scored_in_8_bit(tmp_path):
    """Training views of values 100 and 120 -> a flat 110; a held-out view of 120 is 10 levels
    away: PSNR = 10 log10(255^2 / 100), float64 by hand."""
    images = tmp_path / "scene" / "images"
    images.mkdir(parents=True)
    for name, v in (("a.png", 100), ("b.png", 120), ("c.png", 120)):
        write_image(images / name, np.full((4, 6, 3), v / 255.0, np.float32))
    (tmp_path / "train.txt").write_text("a.png\nb.png\n")
    (tmp_path / "test.txt").write_text("c.png\n")
    assert floor_psnr(tmp_path) == pytest.approx(10 * math.log10(255.0 ** 2 / 100.0), abs=1e-9)
    assert floor_psnr(tmp_path / "absent") is None


def test_scene_interval_takes_the_scene_as_the_unit():
    """Many seeds on one scene must not narrow the interval: differences are averaged per scene
    first. Scene a: +1 (3 seeds), scene b: +3 (1 seed) -> mean +2 over k = 2 scenes."""
    rows = [_rec("a", "x", s, 11.0) for s in range(3)] + [_rec("a", "y", s, 10.0) for s in range(3)]
    rows += [_rec("b", "x", 0, 13.0), _rec("b", "y", 0, 10.0), _rec("b", "y", 1, 99.0)]  # seed 1 unpaired
    iv = scene_level.scene_interval(rows, "x", "y", ["a", "b"])
    assert iv["per_scene"] == {"a": pytest.approx(1.0), "b": pytest.approx(3.0)}
    assert iv["k"] == 2 and iv["mean"] == pytest.approx(2.0) and iv["scenes_ahead"] == 2
    # t(0.975, 1) * std([1, 3], ddof=1) / sqrt(2) = 12.7062 * 1.41421 / 1.41421
    assert iv["hw95"] == pytest.approx(12.706204736, rel=1e-6)
    lp = scene_level.scene_interval([_rec("a", "x", 0, 1, 0.2), _rec("a", "y", 0, 1, 0.3)], "x", "y", ["a"],
                                    "lpips_alex")
    assert lp["scenes_ahead"] == 1 and lp["hw95"] is None  # a lower LPIPS is ahead; one scene: no width


def test_summary_holds_floor_equal_backgrounds_intervals_and_coverage(tmp_path):
    """Through the CLI: with floors.json beside the runs, each view count's measures carry the
    floor row and ``sparse`` − floor, both equal-background pairs, ``sparse`` − every other
    recipe with the scene as the unit, and covered-pixel figures where every run recorded them."""
    rec = tmp_path / "rec"
    (rec / "runs").mkdir(parents=True)
    rows = []
    for scene, lift in (("a", 0.0), ("b", 2.0)):
        for seed in (0, 1):
            rows += [_rec(scene, "sparse", seed, 20.0 + lift, 0.20, coverage=0.7),
                     _rec(scene, "paper-seedcode", seed, 16.0 + lift, 0.30, coverage=0.9),
                     _rec(scene, "paper", seed, 15.0 + lift, 0.32),
                     _rec(scene, "sparse-r13", seed, 17.0 + lift + seed, 0.25),
                     _rec(scene, "paper-bgmean", seed, 19.0 + lift, 0.22, coverage=0.8)]
    for i, r in enumerate(rows):
        (rec / "runs" / f"{i}.json").write_text(json.dumps(r))
    (rec / "floors.json").write_text(json.dumps({"floors": {"a": {"3": 15.0}, "b": {"3": 14.0}}}))
    doc = tmp_path / "t.md"
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--records", str(rec), "summary",
                          "--doc", str(doc)], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    t = json.loads((rec / "summary.json").read_text())["targets"]
    fl = t["floor"]
    assert fl["psnr"] == pytest.approx(14.5) and fl["lead"]["per_scene"] == {"a": 5.0, "b": 8.0} and fl["met"]
    black, mean = t["equal_background"]
    assert (black["background"], black["ours"], black["base"]) == ("black", "sparse-r13", "paper-seedcode")
    assert black["diff"]["psnr"]["mean"] == pytest.approx(1.5) and black["diff"]["psnr"]["k"] == 2
    assert black["met"]  # +1.5, both scenes exactly +1.5: interval of zero width above 0; LPIPS lower
    assert mean["diff"]["psnr"]["mean"] == pytest.approx(1.0) and mean["met"]
    assert t["scene_level"]["paper-seedcode"]["mean"] == pytest.approx(4.0)
    assert set(t["coverage"]) == {"sparse", "paper-seedcode", "paper-bgmean"}  # sparse-r13 and paper recorded none
    assert t["coverage"]["sparse"]["coverage"] == pytest.approx(0.7)
    assert t["coverage"]["paper-seedcode"]["psnr_covered"] == pytest.approx(18.0)
    text = doc.read_text()
    assert "floor, a flat image of the training views' mean colour: 14.50 dB" in text
    assert "at equal background (black): `sparse-r13` 18.50 against `paper-seedcode` 17.00" in text
    assert "each at its own background (not a like-for-like" in text


def test_summary_without_floors_says_how_to_measure_them(tmp_path):
    rec = tmp_path / "rec"
    (rec / "runs").mkdir(parents=True)
    for i, r in enumerate([_rec("a", "sparse", 0, 20.0), _rec("a", "paper", 0, 18.0)]):
        (rec / "runs" / f"{i}.json").write_text(json.dumps(r))
    doc = tmp_path / "t.md"
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--records", str(rec), "summary",
                          "--doc", str(doc)], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert json.loads((rec / "summary.json").read_text())["targets"]["floor"] is None
    assert "python -m experiments.sparse_views floor" in doc.read_text()


def test_floor_cli_scores_a_generated_cell_and_refuses_unknown_scenes(tmp_path):
    """``floor`` through the CLI on a small generated scene: the cell's split is made, nothing is
    trained, floors.json gets the scene at its view count; a second call keeps it; an unknown
    scene name is exit 2 in one line."""
    f = tmp_path / "p.yaml"
    f.write_text("scenes:\n- {name: tiny, role: evaluation, kind: synthetic, views: [3],\n"
                 "   generate: [python, -m, camio, synth, --out, '{out}', --views, '16', --width, '128']}\n")
    cmd = [sys.executable, "-m", "experiments.sparse_views", "--protocol", str(f), "--records", str(tmp_path / "rec"),
           "floor", "--work", str(tmp_path / "w")]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    floors = json.loads((tmp_path / "rec" / "floors.json").read_text())["floors"]
    assert set(floors) == {"tiny"} and math.isfinite(floors["tiny"]["3"]) and floors["tiny"]["3"] > 5
    assert not (tmp_path / "w" / "tiny_n3" / "bridge").exists()  # no seed, no training
    again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert again.returncode == 0 and "floor tiny" not in again.stdout
    bad = subprocess.run(cmd + ["--scenes", "tinyy"], cwd=REPO, capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "tinyy" in bad.stderr, bad.stderr


def test_coverage_adds_covered_ssim_and_lpips_only_where_every_run_scored_them():
    scenes = ["a", "b"]
    rows = [_rec(s, "sparse", k, 20.0 + k, coverage=0.8) for s in scenes for k in (0, 1)]
    for i, r in enumerate(rows):
        r["curve"]["ssim_covered"] = [0.5 + 0.1 * i]
        r["curve"]["lpips_covered"] = [0.2]
    old = [_rec(s, "paper", 0, 18.0, coverage=0.9) for s in scenes]  # before the trainer scored them
    out = scene_level.coverage(rows + old, scenes)
    # per scene the mean over seeds (0.55 and 0.75), then over the scenes
    assert out["sparse"]["ssim_covered"] == pytest.approx(0.65, abs=1e-12)
    assert out["sparse"]["lpips_covered"] == pytest.approx(0.2, abs=1e-12)
    assert set(out["paper"]) == {"coverage", "psnr_covered", "psnr"}
    rows[0]["curve"]["lpips_covered"] = [None]  # LPIPS off in one run: no covered LPIPS mean
    assert "lpips_covered" not in scene_level.coverage(rows, scenes)["sparse"]
