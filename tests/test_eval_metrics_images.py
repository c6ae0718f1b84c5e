"""The ``images`` evaluation: matching, errors, JSON record, LPIPS missing vs present."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from camio.images import write_image
from evaluation.metrics.images_cli import add_parser, evaluate_images, main, match_images
from imgmetrics.lpips import LPIPS
from imgmetrics.psnr_ssim import PSNR_CAP_DB
from tests._lpips_weights import random_alex_weights

pytestmark = pytest.mark.usefixtures("core_threads")


@pytest.fixture
def no_lpips_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "empty_cache"))
    monkeypatch.delenv("LPIPS_WEIGHTS_DIR", raising=False)


def _img(seed: int, h: int = 20, w: int = 24) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3)).astype(np.uint8)


def _folders(tmp_path, names_pred, names_gt, size=(20, 24)):
    pred, gt = tmp_path / "pred", tmp_path / "gt"
    for i, n in enumerate(names_gt):
        write_image(gt / n, _img(i, *size))
    for i, n in enumerate(names_pred):
        write_image(pred / n, _img(100 + i, *size))
    return pred, gt


def test_match_by_stem_across_extensions(tmp_path):
    pred, gt = _folders(tmp_path, ["b.png", "a.png"], ["a.tif", "b.tif"])
    assert match_images(pred, gt) == [("a.png", "a.tif"), ("b.png", "b.tif")]


def test_unmatched_names_are_listed(tmp_path):
    pred, gt = _folders(tmp_path, ["a.png", "extra.png"], ["a.png", "lost.png"])
    with pytest.raises(ValueError, match=r"only in .*pred.*extra\.png.*only in .*gt.*lost\.png"):
        match_images(pred, gt)


def test_duplicate_stem_and_empty_folder(tmp_path):
    pred, gt = _folders(tmp_path, ["a.png", "a.tif"], ["a.png"])
    with pytest.raises(ValueError, match="two images with the stem 'a'"):
        match_images(pred, gt)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no images"):
        match_images(tmp_path / "empty", gt)
    with pytest.raises(ValueError, match="no images"):
        match_images(gt, tmp_path / "empty")
    with pytest.raises(FileNotFoundError):
        match_images(tmp_path / "missing", gt)


def test_size_mismatch_is_an_error(tmp_path, no_lpips_weights):
    pred, gt = tmp_path / "pred", tmp_path / "gt"
    write_image(gt / "a.png", _img(0, 20, 24))
    write_image(pred / "a.png", _img(1, 20, 25))
    with pytest.raises(ValueError, match=r"size mismatch for a\.png.*25x20.*24x20"):
        evaluate_images(pred, gt, tmp_path / "m.json")
    assert not (tmp_path / "m.json").exists()


def test_record_without_lpips_weights(tmp_path, no_lpips_weights):
    pred, gt = _folders(tmp_path, ["0.png", "1.png"], ["0.png", "1.png"])
    write_image(pred / "1.png", _img(1))  # identical to gt/1.png -> PSNR inf -> capped
    out = tmp_path / "res" / "metrics.json"
    res = evaluate_images(pred, gt, out)
    data = json.loads(out.read_text())
    for key in ("psnr", "ssim", "lpips_alex", "lpips_vgg", "n_images", "per_image", "psnr_capped"):
        assert key in data
    assert data["lpips_alex"] is None and data["lpips_vgg"] is None  # missing, never 0
    assert all(r["lpips_alex"] is None and r["lpips_vgg"] is None for r in data["per_image"])
    assert data["n_images"] == 2 and data["psnr_capped"] == ["1.png"]
    p0 = data["per_image"][0]["psnr"]
    a = _img(100).astype(np.float64) / 255
    b = _img(0).astype(np.float64) / 255
    # 1e-6 dB: read_image gives float32 pixels (k / 255 rounded to float32), the reference is float64
    assert p0 == pytest.approx(-10 * math.log10(np.mean((a - b) ** 2)), abs=1e-6)
    assert data["per_image"][1]["psnr"] == PSNR_CAP_DB and data["per_image"][1]["ssim"] == pytest.approx(1.0)
    assert data["psnr"] == pytest.approx((p0 + PSNR_CAP_DB) / 2)
    assert res["per_image"] == data["per_image"]


def test_record_with_lpips_weights(tmp_path, no_lpips_weights):
    wdir = random_alex_weights(tmp_path / "weights")
    pred, gt = _folders(tmp_path, ["0.png", "1.png"], ["0.png", "1.png"], size=(40, 40))
    write_image(pred / "1.png", _img(1, 40, 40))
    res = evaluate_images(pred, gt, None, lpips_nets=("alex",), lpips_weights=wdir)
    assert res["per_image"][0]["lpips_alex"] > 0 and res["per_image"][1]["lpips_alex"] == 0.0
    assert res["lpips_alex"] == pytest.approx(res["per_image"][0]["lpips_alex"] / 2)
    assert res["lpips_vgg"] is None and res["lpips_weights"]["vgg"] is None  # not requested
    assert res["lpips_weights"]["alex"].endswith("alex.safetensors")


def test_cli_parsers(tmp_path, no_lpips_weights):
    pred, gt = _folders(tmp_path, ["x.png"], ["x.png"])
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers(dest="cmd", required=True))
    args = parser.parse_args(["images", "--pred", str(pred), "--gt", str(gt), "--out", str(tmp_path / "a.json"),
                              "--lpips-nets"])
    assert args.func(args) == 0 and json.loads((tmp_path / "a.json").read_text())["n_images"] == 1
    assert main(["--pred", str(pred), "--gt", str(gt), "--out", str(tmp_path / "b.json")]) == 0
    assert json.loads((tmp_path / "b.json").read_text())["lpips_vgg"] is None


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_works_from_its_smallest_side_and_refuses_below(net):
    from imgmetrics.lpips import MIN_SIDE

    m = LPIPS(net)
    side = MIN_SIDE[net]
    x, y = torch.rand(1, 3, side, side + 5), torch.rand(1, 3, side, side + 5)
    assert torch.isfinite(m(x, y)).all()
    with pytest.raises(ValueError, match=f"LPIPS-{net} needs images at least {side} px a side"):
        m(x[..., : side - 1, :], y[..., : side - 1, :])


def test_images_cli_refuses_lpips_on_images_too_small_for_it(tmp_path, no_lpips_weights):
    from tests._cli import refused, run

    wdir = tmp_path / "weights"
    wdir.mkdir()
    save_file(LPIPS("alex").state_dict(), str(wdir / "alex.safetensors"), metadata={"net": "alex"})
    pred, gt = _folders(tmp_path, ["0.png"], ["0.png"])  # 24x20: below AlexNet's smallest side
    out = tmp_path / "m.json"
    proc = run(["-m", "evaluation", "images", "--pred", str(pred), "--gt", str(gt), "--out", str(out),
                "--lpips-nets", "alex", "--lpips-weights", str(wdir)])
    refused(proc, "LPIPS-alex needs images at least 31 px a side", "24x20", "--lpips-nets")
    assert not out.exists()
    # without LPIPS the same images are scored
    assert run(["-m", "evaluation", "images", "--pred", str(pred), "--gt", str(gt), "--out", str(out),
                "--lpips-nets"]).returncode == 0 and out.is_file()
