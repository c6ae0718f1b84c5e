"""The renders' accumulated opacity and the figures over the covered pixels, through the commands a
user runs: ``splat_train render --alpha`` writes ``alpha/<stem>.png`` beside each render (16-bit gray, the
opacity the renderer computed), and ``evaluation images --alpha-dir`` scores the covered pixels into
metrics.json (keys always present, null without ``--alpha-dir``); a missing or mis-sized alpha image is
one line naming it."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from _cli import refused, run
from _train_scene import write_scene
from camio.alpha import read_alpha
from camio.colmap import read_model
from camio.images import image_size, list_images, read_image, write_image
from camio.ply import read_gaussian_ply
from imgmetrics.covered import COVERED_ALPHA
from splat_train.export import camera_tensors, render_params
from splat_train.gaussians import params_from_cloud

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

COVERED_KEYS = {"psnr", "ssim", "lpips_alex", "lpips_vgg"}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The seed cloud of a small scene rendered into its two held-out cameras."""
    root = tmp_path_factory.mktemp("alpha")
    paths = write_scene(root / "scene", n_views=3, width=40, height=30, n_test=2)
    out = root / "renders"
    proc = run(["-m", "splat_train", "render", "--model", str(paths["seed"]), "--cameras", str(paths["test_cameras"]),
                "--images", str(paths["test_images"]), "--out", str(out), "--background", "0,0,0", "--alpha"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return paths, out


def test_render_writes_no_alpha_unless_asked(rendered, tmp_path):
    paths, _ = rendered
    out = tmp_path / "plain"
    proc = run(["-m", "splat_train", "render", "--model", str(paths["seed"]), "--cameras", str(paths["test_cameras"]),
                "--images", str(paths["test_images"]), "--out", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert list_images(out) == sorted(list_images(paths["test_images"])) and not (out / "alpha").exists()


def test_render_writes_the_opacity_beside_each_render(rendered):
    paths, out = rendered
    assert list_images(out) == sorted(list_images(paths["test_images"]))  # the RGB renders, unchanged
    assert sorted(p.name for p in (out / "alpha").iterdir()) == list_images(out)
    import OpenImageIO as oiio

    cloud = read_gaussian_ply(paths["seed"])
    params = params_from_cloud(cloud, sh_degree=cloud.sh_degree)
    shares = []
    for cam in read_model(paths["test_cameras"]).cameras:
        f = out / "alpha" / cam.name
        inp = oiio.ImageInput.open(str(f))
        spec = inp.spec()
        inp.close()
        assert (spec.nchannels, spec.format.basetype) == (1, oiio.UINT16), f
        stored = read_alpha(f)
        assert stored.shape == (cam.height, cam.width) and 0.0 <= stored.min() and stored.max() <= 1.0
        cw, K = camera_tensors(cam)
        alpha = render_params(params, cloud.sh_degree, cw, K, cam.width, cam.height, torch.zeros(3))["alpha"]
        assert np.abs(stored - alpha.detach().double().numpy()).max() <= 0.5 / 65535 + 1e-7, f
        shares.append(float((stored >= COVERED_ALPHA).mean()))
    assert 0.0 < min(shares) and max(shares) < 1.0, shares  # a view the model covers in part


def _metrics(rendered, tmp_path, *extra):
    paths, out = rendered
    res = tmp_path / "metrics.json"
    proc = run(["-m", "evaluation", "images", "--pred", str(out), "--gt", str(paths["test_images"]),
                "--lpips-nets", "--out", str(res), *extra])
    return proc, res


def test_images_alpha_scores_the_covered_pixels(rendered, tmp_path):
    paths, out = rendered
    proc, res = _metrics(rendered, tmp_path, "--alpha-dir", str(out / "alpha"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = json.loads(res.read_text())
    assert data["covered_alpha"] == COVERED_ALPHA and data["alpha_dir"] == str(out / "alpha")
    shares = []
    for rec in data["per_image"]:
        alpha = read_alpha(out / "alpha" / rec["pred"])
        mask = alpha >= COVERED_ALPHA
        shares.append(mask.mean())
        assert rec["coverage"] == pytest.approx(mask.mean(), abs=1e-12)
        pred = read_image(out / rec["pred"]).astype(np.float64)
        gt = read_image(paths["test_images"] / rec["name"]).astype(np.float64)
        mse = ((pred - gt)[mask] ** 2).mean()
        assert rec["covered"]["psnr"] == pytest.approx(-10 * np.log10(mse), abs=1e-9)
        assert set(rec["covered"]) == COVERED_KEYS and rec["covered"]["lpips_alex"] is None  # LPIPS not asked
        # the covered PSNR is not the full-image one: the uncovered background is left out
        assert rec["covered"]["psnr"] != pytest.approx(rec["psnr"], abs=1e-6)
    assert data["coverage"] == pytest.approx(np.mean(shares), abs=1e-12)
    assert data["covered"]["psnr"] == pytest.approx(np.mean([r["covered"]["psnr"] for r in data["per_image"]]))
    assert data["covered"]["ssim"] == pytest.approx(np.mean([r["covered"]["ssim"] for r in data["per_image"]]))
    assert data["covered"]["lpips_vgg"] is None


def test_images_without_alpha_keeps_the_keys_null(rendered, tmp_path):
    proc, res = _metrics(rendered, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = json.loads(res.read_text())
    assert all(data[k] is None for k in ("alpha_dir", "covered_alpha", "coverage", "covered"))
    assert all(r["coverage"] is None and r["covered"] is None for r in data["per_image"])


def test_a_missing_alpha_image_is_refused_naming_it(rendered, tmp_path):
    _, out = rendered
    alpha = tmp_path / "alpha"
    shutil.copytree(out / "alpha", alpha)
    gone = sorted(alpha.iterdir())[1]
    gone.unlink()
    proc, res = _metrics(rendered, tmp_path, "--alpha-dir", str(alpha))
    refused(proc, str(gone), "missing")
    assert not res.exists()


def test_an_alpha_image_of_another_size_is_refused_naming_it(rendered, tmp_path):
    _, out = rendered
    alpha = tmp_path / "alpha"
    shutil.copytree(out / "alpha", alpha)
    bad = sorted(alpha.iterdir())[0]
    w, h = image_size(bad)
    write_image(bad, np.ones((h, w + 1)), bits=16)
    proc, res = _metrics(rendered, tmp_path, "--alpha-dir", str(alpha))
    refused(proc, str(bad), "size mismatch")
    assert not res.exists()
