"""``python -m evaluation floor``: the flat image of the training views' mean colour, scored on
the held-out views exactly as ``evaluation images`` scores a render; its colour's one definition
(imgmetrics.floor); its refusals; the workflow's floor.json per (scene, n)."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from camio.images import write_image
from experiments.sparse_views.floor import floor_psnr
from imgmetrics.floor import flat_colour, flat_image
from tests._cli import ROOT, refused, run
from tests._lpips_weights import random_alex_weights

SNAKEMAKE = shutil.which("snakemake")


def _scene(root: Path, n_train: int = 3, n_test: int = 2) -> dict:
    """A folder of random 8-bit PNGs (training views of two sizes), a train list and a folder of
    held-out views of another size; returns the paths and the uint8 arrays."""
    rng = np.random.default_rng(7)
    images, gt = root / "images", root / "test_images"
    train = {}
    for i in range(n_train):
        h, w = (20, 24) if i % 2 else (17, 31)
        a = (rng.random((h, w, 3)) ** (0.5 + i) * 255).round().astype(np.uint8)
        train[f"v{i}.png"] = a
        write_image(images / f"v{i}.png", a)
    test = {}
    for i in range(n_test):
        a = rng.integers(0, 256, (40, 46, 3), dtype=np.uint8)  # AlexNet-LPIPS needs >= ~32 px
        test[f"t{i}.png"] = a
        write_image(gt / f"t{i}.png", a)
        write_image(images / f"t{i}.png", a)
    write_image(images / "unused.png", rng.integers(0, 256, (20, 24, 3), dtype=np.uint8))
    (root / "train.txt").write_text("".join(f"{n}\n" for n in train))
    return {"images": images, "gt": gt, "train_txt": root / "train.txt", "train": train, "test": test}


def _floor(s: dict, out: Path, *extra: str):
    return run(["-m", "evaluation", "floor", "--images", str(s["images"]), "--train-names", str(s["train_txt"]),
                "--gt", str(s["gt"]), "--out", str(out), *extra])


def test_floor_colour_is_the_rounded_mean_of_each_views_mean():
    """Each view counts once whatever its size (a 2x2 view of 0 and a 1x1 view of 90: 45, not
    the pixel mean 18); the mean is rounded half to even; the flat image is that colour, uint8."""
    a, b = np.zeros((2, 2, 3), np.uint8), np.full((1, 1, 3), 90, np.uint8)
    b[..., 1], b[..., 2] = 5, 6  # channel means: 2.5 -> 2, 3 -> 3
    assert flat_colour([a, b]).tolist() == [45, 2, 3]
    img = flat_image([45, 2, 3], 5, 7)
    assert img.dtype == np.uint8 and img.shape == (5, 7, 3) and (img == [45, 2, 3]).all()
    with pytest.raises(ValueError, match="no training view"):
        flat_colour([])
    with pytest.raises(ValueError, match="8-bit RGB"):
        flat_colour([a.astype(np.float32)])


def test_flat_image_in_float_is_what_reading_its_png_gives(tmp_path):
    """camio.images.from_uint8 gives, for every 8-bit code, the float32 read_image returns for
    a PNG of it (not code / 255, which differs in the last bit for some codes)."""
    from camio.images import from_uint8, read_image

    codes = np.arange(256, dtype=np.uint8).reshape(16, 16, 1).repeat(3, axis=2)
    write_image(tmp_path / "codes.png", codes)
    assert np.array_equal(from_uint8(codes), read_image(tmp_path / "codes.png"))


def test_floor_cli_psnr_equals_a_float64_reference(tmp_path):
    """Through the CLI: the colour is the rounded mean of the training views' means, and each
    held-out view's PSNR (and the mean) is the float64 PSNR of that flat 8-bit image against
    it; LPIPS not asked for is null; the sparse-view benchmark's floor_psnr agrees."""
    s = _scene(tmp_path)
    proc = _floor(s, tmp_path / "floor.json", "--lpips-nets")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rec = json.loads((tmp_path / "floor.json").read_text())
    views = [v.astype(np.float64) for v in s["train"].values()]
    colour = np.round(np.mean([v.reshape(-1, 3).mean(0) for v in views], axis=0))
    assert rec["colour"] == [int(c) for c in colour]
    psnrs = []
    for name, gt in sorted(s["test"].items()):
        mse = np.mean((gt.astype(np.float64) / 255.0 - colour / 255.0) ** 2)
        psnrs.append(10 * math.log10(1.0 / mse))
    assert [r["name"] for r in rec["per_image"]] == sorted(s["test"])
    assert [r["psnr"] for r in rec["per_image"]] == pytest.approx(psnrs, rel=1e-9, abs=1e-6)
    assert rec["psnr"] == pytest.approx(np.mean(psnrs), abs=1e-6)
    assert rec["n_images"] == 2 and rec["train_names"] == sorted(s["train"])
    assert rec["lpips_alex"] is None and rec["lpips_vgg"] is None
    assert rec["lpips_weights"] == {"alex": None, "vgg": None} and rec["psnr_cap_db"] == 100.0
    assert 0 < rec["ssim"] < 1 and rec["wall_time_s"] >= 0
    (tmp_path / "test.txt").write_text("t0.png\nt1.png\n")
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "images").symlink_to(s["images"])
    assert floor_psnr(tmp_path) == pytest.approx(rec["psnr"], abs=1e-6)


def test_floor_is_scored_like_a_render_of_the_flat_image(tmp_path, monkeypatch):
    """The floor of each held-out view equals `evaluation images` on a PNG render of the flat
    image (PSNR, SSIM and LPIPS, bit for bit): one scoring for both."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "empty_cache"))
    monkeypatch.delenv("LPIPS_WEIGHTS_DIR", raising=False)
    wdir = random_alex_weights(tmp_path / "weights")
    s = _scene(tmp_path)
    lp = ("--lpips-nets", "alex", "--lpips-weights", str(wdir))
    assert _floor(s, tmp_path / "floor.json", *lp).returncode == 0
    floor = json.loads((tmp_path / "floor.json").read_text())
    renders = tmp_path / "renders"
    for name, gt in s["test"].items():
        write_image(renders / name, flat_image(floor["colour"], *gt.shape[:2]))
    proc = run(["-m", "evaluation", "images", "--pred", str(renders), "--gt", str(s["gt"]),
                "--out", str(tmp_path / "metrics.json"), *lp])
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    keys = ("psnr", "ssim", "lpips_alex", "lpips_vgg")
    assert [{k: r[k] for k in keys} for r in floor["per_image"]] == [{k: r[k] for k in keys} for r in metrics["per_image"]]
    assert floor["lpips_alex"] > 0 and floor["lpips_vgg"] is None
    assert floor["lpips_weights"] == metrics["lpips_weights"]


def _no_train(s, tmp_path):
    s["train_txt"].write_text("v0.png\nmissing.png\n")
    return "missing.png"


def _empty_train(s, tmp_path):
    s["train_txt"].write_text("\n# no names\n")
    return "names no image"


def _no_images_folder(s, tmp_path):
    s["images"] = tmp_path / "nowhere"
    return "nowhere"


def _no_gt_folder(s, tmp_path):
    s["gt"] = tmp_path / "no_test_images"
    return "no_test_images"


def _gt_without_images(s, tmp_path):
    s["gt"] = tmp_path / "empty_test"
    s["gt"].mkdir()
    return "no images"


@pytest.mark.parametrize("spoil", [_no_train, _empty_train, _no_images_folder, _no_gt_folder, _gt_without_images],
                         ids=["train-name-not-in-images", "empty-train-list", "missing-images-folder",
                              "missing-gt-folder", "gt-folder-without-images"])
def test_floor_refusals(tmp_path, spoil):
    """Bad input: exit 2, one line naming what is wrong, no floor.json written."""
    s = _scene(tmp_path)
    needle = spoil(s, tmp_path)
    out = tmp_path / "out" / "floor.json"
    refused(_floor(s, out, "--lpips-nets"), needle)
    assert not out.exists()


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_workflow_makes_floor_json_per_scene_and_view_count(tmp_path):
    """The rule floor makes R/{dataset}/{scene}/n{n}/floor.json from the prepared scene, the n
    training names and the held-out images, and the tables ask for one per (scene, n)."""
    cfg = {"results": "results", "datasets": {"synthetic": {"scenes": {"tiny": {"synth": {"views": 16, "width": 64}}}}},
           "views": [3, 4], "initialisers": ["oracle"], "train": {"iterations": 10},
           "evaluation": {"lpips_nets": []}}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    base = [SNAKEMAKE, "--snakefile", str(ROOT / "Snakefile"), "--directory", str(tmp_path),
            "--configfile", str(tmp_path / "config.yaml"), "--cores", "1"]
    plan = subprocess.run([*base, "-n", "results/tables/tables.md"], capture_output=True, text=True, timeout=300)
    assert plan.returncode == 0, plan.stdout[-3000:] + plan.stderr[-3000:]
    planned = sorted(ln.split()[-1] for ln in (plan.stdout + plan.stderr).splitlines()
                     if ln.strip().startswith("output:") and ln.strip().endswith("floor.json"))
    assert planned == [f"results/synthetic/tiny/n{n}/floor.json" for n in (3, 4)]
    target = "results/synthetic/tiny/n3/floor.json"
    proc = subprocess.run([*base, target], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    rec = json.loads((tmp_path / target).read_text())
    scene = tmp_path / "results" / "synthetic" / "tiny"
    names = (scene / "n3" / "train.txt").read_text().split()
    assert rec["train_names"] == sorted(names) and rec["n_images"] == len(json.loads((scene / "split.json").read_text())["test"])
    from camio.images import read_image_uint8

    assert rec["colour"] == flat_colour(read_image_uint8(scene / "synth" / "images" / n) for n in names).tolist()
    assert rec["lpips_alex"] is None and "floor over" in (scene / "logs" / "floor_n3.log").read_text()
