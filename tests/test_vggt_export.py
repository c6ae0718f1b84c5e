"""CLI end to end with the tiny fixture model: predictions.npz schema, sparse/0 read back by
pycolmap with K consistent with the original image sizes, timing.json, bad inputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from _oiio_write import write_raw as _write

from vggt_init.__main__ import main
from vggt_init.export import OPTIONAL_KEYS, PREDICTION_KEYS, select_points
from vggt_init.geometry import unproject_depth

FIX = Path(__file__).parent / "data" / "vggt" / "shared"
SIZE = 56  # network width: 4 patches, keeps the tiny model fast




@pytest.fixture()
def scene(tmp_path):
    """A few tiny images of different kinds and sizes."""
    rng = np.random.default_rng(0)
    d = tmp_path / "images"
    d.mkdir()
    yy, xx = np.mgrid[0:40, 0:60]
    base = np.stack([xx * 4, yy * 6, (xx + yy) * 2], -1).clip(0, 255).astype(np.uint8)
    _write(d / "a_rgb.png", base)
    _write(d / "b_gray.png", base[..., 0].copy())
    rgba = np.concatenate([base, rng.integers(0, 256, (40, 60, 1), dtype=np.uint8)], -1)
    _write(d / "c_rgba.png", rgba)
    _write(d / "d_rgb16.png", base.astype(np.uint16) * 257, "uint16")
    shutil.copy(FIX / "images" / "s2_portrait_48x64.png", d / "e_portrait.png")
    return d


def _cli(images: Path, out: Path, *extra: str) -> int:
    # In-process, so --no-retain-memory leaves this pytest process's malloc settings alone;
    # test_runtime_memory.py runs the CLI with them, in a subprocess.
    return main(["--images", str(images), "--out", str(out), "--model-config", str(FIX / "config.json"),
                 "--checkpoint", str(FIX / "weights.safetensors"), "--image-size", str(SIZE),
                 "--threads", "2", "--max-points", "500", "--no-retain-memory", *extra])


def _check_colmap(out: Path, pred) -> None:
    from camio.colmap import read_model

    model = read_model(out / "sparse" / "0")
    by_name = {c.name: c for c in model.cameras}
    assert sorted(by_name) == sorted(pred["image_names"].tolist())
    assert 0 < len(model.points) <= 500
    assert np.isfinite(model.points).all()
    for i, name in enumerate(pred["image_names"]):
        cam = by_name[str(name)]
        w, h = pred["image_sizes_original"][i]
        assert (cam.width, cam.height) == (w, h)
        np.testing.assert_allclose(cam.K, pred["intrinsics_original"][i], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(cam.cam_from_world, pred["cam_from_world"][i], rtol=0, atol=1e-6)
        # K must refer to the original size: mapping the original image's corners through the
        # resize/crop/pad lands on the network image the same way the K's do.
        K_net, K = pred["intrinsics"][i].astype(np.float64), cam.K
        S, Hn, Wn = pred["world_points"].shape[:3]
        sx = K_net[0, 0] / K[0, 0]
        sy = K_net[1, 1] / K[1, 1]
        ox, oy = K_net[0, 2] - sx * K[0, 2], K_net[1, 2] - sy * K[1, 2]
        # the original image maps onto a whole-pixel resized image at a whole-pixel offset
        # (padding >= 0, or a centred crop < 0) inside the Wn x Hn network input
        for scaled, off, n_in in ((sx * w, ox, Wn), (sy * h, oy, Hn)):
            assert scaled == pytest.approx(round(scaled), abs=1e-3)
            assert off == pytest.approx(round(off), abs=1e-3)
            assert (0 <= round(off) and round(off) + round(scaled) <= n_in) or \
                round(off) == -((round(scaled) - n_in) // 2)


def test_cli_point_head_end_to_end(scene, tmp_path):
    out = tmp_path / "out"
    assert _cli(scene, out) == 0
    pred = np.load(out / "predictions.npz")
    assert set(pred.files) == set(PREDICTION_KEYS)
    S, H, W = pred["world_points"].shape[:3]
    assert S == 5 and W == SIZE and H % 14 == 0
    expect = {"cam_from_world": ((S, 3, 4), np.float32), "intrinsics": ((S, 3, 3), np.float32),
              "intrinsics_original": ((S, 3, 3), np.float64), "image_sizes_original": ((S, 2), np.int64),
              "world_points": ((S, H, W, 3), np.float32), "world_points_conf": ((S, H, W), np.float32),
              "colors": ((S, H, W, 3), np.uint8)}
    for k, (shape, dtype) in expect.items():
        assert pred[k].shape == shape and pred[k].dtype == dtype, k
    assert pred["image_names"].dtype.kind == "U"
    assert pred["image_names"].tolist() == sorted(p.name for p in scene.iterdir())
    assert pred["image_sizes_original"].tolist() == [[60, 40]] * 4 + [[48, 64]]
    assert (pred["world_points_conf"] > 1).all()
    # network intrinsics: principal point at the input centre
    np.testing.assert_allclose(pred["intrinsics"][:, 0, 2], W / 2)
    np.testing.assert_allclose(pred["intrinsics"][:, 1, 2], H / 2)
    _check_colmap(out, pred)
    # landscape 60x40 images are resized to 56 x round(40*56/60/14)*14 = 56 x 42, then the
    # portrait one (56 x 70 -> cropped to 56) makes the batch 56 x 56: 7 rows of padding on top
    K0 = pred["intrinsics_original"][0]
    Kn = pred["intrinsics"][0].astype(np.float64)
    np.testing.assert_allclose(K0[0, 0], Kn[0, 0] * 60 / 56, rtol=1e-6)
    np.testing.assert_allclose(K0[1, 1], Kn[1, 1] * 40 / 42, rtol=1e-6)
    np.testing.assert_allclose(K0[:2, 2], [(Kn[0, 2] - 0) * 60 / 56, (Kn[1, 2] - 7) * 40 / 42], rtol=1e-6)
    timing = json.loads((out / "timing.json").read_text())
    t = timing["wall_time_s"]
    heads = ("forward.aggregator", "forward.camera_head", "forward.point_head")
    assert t["forward"] > 0 and all(t[k] > 0 for k in heads)
    # the parts are timed inside their whole: the heads inside the forward, the stages inside the run
    assert sum(t[k] for k in heads) <= t["forward"]
    assert sum(t[k] for k in ("preprocess", "load_model", "forward", "postprocess", "export")) <= t["total"]
    assert "forward.depth_head" not in timing["wall_time_s"]
    assert timing["heads_built"] == ["camera", "point"]
    assert timing["peak_rss_mb"] > 0 and timing["nonfinite_total"] == 0 and timing["flagged"] is False
    assert timing["retain_freed_memory"] is False  # --no-retain-memory


def test_cli_depth_route_single_image_list_bf16(scene, tmp_path):
    out = tmp_path / "out"
    (tmp_path / "list.txt").write_text("# one image\na_rgb.png\n")
    assert _cli(scene, out, "--points-from", "depth", "--image-list", str(tmp_path / "list.txt"),
                "--mode", "pad", "--dtype", "bf16") == 0
    pred = np.load(out / "predictions.npz")
    assert set(pred.files) == set(PREDICTION_KEYS) | set(OPTIONAL_KEYS)
    assert pred["world_points"].shape == (1, SIZE, SIZE, 3)
    assert pred["depth"].shape == (1, SIZE, SIZE) and (pred["depth"] > 0).all()
    np.testing.assert_array_equal(pred["world_points_conf"], pred["depth_conf"])
    wp = unproject_depth(pred["depth"], pred["cam_from_world"], pred["intrinsics"]).astype(np.float32)
    np.testing.assert_allclose(pred["world_points"], wp, rtol=1e-6, atol=1e-6)
    # pad mode, 60x40 -> 56x42 centred in 56x56: 7 rows of padding
    np.testing.assert_array_equal(pred["colors"][0, :7], 255)
    _check_colmap(out, pred)
    timing = json.loads((out / "timing.json").read_text())
    assert timing["heads_built"] == ["camera", "depth"] and "forward.point_head" not in timing["wall_time_s"]
    assert timing["dtype"] == "bf16" and timing["num_images"] == 1


def test_sparse_points_exclude_padding_and_rank_by_confidence():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(2, 4, 5, 3))
    conf = rng.uniform(1, 5, size=(2, 4, 5))
    conf[0, 0, 0] = 100.0  # most confident, but on padding
    pts[1, 1, 1] = np.nan
    conf[1, 1, 1] = 99.0
    cols = rng.integers(0, 256, (2, 4, 5, 3), dtype=np.uint8)
    valid = np.ones((2, 4, 5), bool)
    valid[0, 0] = False
    p, c, s = select_points(pts, conf, cols, valid, 10)
    assert len(p) == 10 and np.all(np.diff(s) <= 0)
    assert s[0] < 99.0
    ok = valid & np.isfinite(pts).all(-1)
    np.testing.assert_allclose(s, np.sort(conf[ok])[::-1][:10])


def test_bad_inputs_fail_clearly(tmp_path, capfd, monkeypatch):
    """Errors exit with code 2 and one log line naming the problem (the CLI logs to stderr)."""
    d = tmp_path / "imgs"
    d.mkdir()
    _write(d / "tiny.png", np.zeros((10, 30, 3), np.uint8))
    assert _cli(d, tmp_path / "o1") == 2
    assert "smaller than one 14 px patch" in capfd.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _cli(empty, tmp_path / "o2") == 2
    assert "no images" in capfd.readouterr().err

    ok = tmp_path / "ok"
    ok.mkdir()
    _write(ok / "x.png", np.full((30, 30, 3), 100, np.uint8))
    assert _cli(ok, tmp_path / "o3", "--max-memory-gb", "0.001") == 2
    err = capfd.readouterr().err
    assert "MemoryBudgetError" in err and "use fewer images" in err
    assert not (tmp_path / "o3" / "predictions.npz").exists()

    # no checkpoint anywhere, offline: one clear error naming where to put the file
    monkeypatch.delenv("VGGT_CHECKPOINT", raising=False)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr("vggt_init.checkpoint._hf_cache_lookup", lambda repo, names: None)
    rc = main(["--images", str(ok), "--out", str(tmp_path / "o4"), "--model-config", str(FIX / "config.json"),
               "--image-size", str(SIZE)])
    assert rc == 2
    err = capfd.readouterr().err
    assert "CheckpointNotFoundError" in err and "VGGT_CHECKPOINT" in err


@pytest.mark.parametrize("dtype", ["fp32", "bf16"])
def test_fp32_forward_runs_without_tf32(scene, tmp_path, monkeypatch, dtype):
    """--dtype fp32 is float32 throughout: the forward runs with torch's TF32 switches off
    (cuDNN convolutions default to TF32 on CUDA: 1.3e-3 on the fixture point map, H100) and
    the caller's switches come back after; bf16 leaves them as the caller set them."""
    from vggt_init.model import VGGT

    seen = []
    forward = VGGT.forward

    def spy(self, *a, **k):
        seen.append((torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32))
        return forward(self, *a, **k)

    monkeypatch.setattr(VGGT, "forward", spy)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", True)
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", True)
    assert _cli(scene, tmp_path / "out", "--dtype", dtype) == 0
    assert seen == [(False, False) if dtype == "fp32" else (True, True)]
    assert torch.backends.cuda.matmul.allow_tf32 and torch.backends.cudnn.allow_tf32
