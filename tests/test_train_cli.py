"""python -m splat_train end to end on a tiny generated scene (train, resume, render)."""

import json
import re

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from _train_scene import write_scene
from camio.images import read_image
from splat_train.__main__ import main


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_cli_train_then_render(tmp_path, capsys):
    sc = write_scene(tmp_path / "scene", n_views=5, width=32, height=24, n_test=2)
    (tmp_path / "list.txt").write_text("# training subset\nview_00.png\nview_02.png\n\nview_04.png\n")
    out = tmp_path / "out"
    cfg = json.dumps({"densify_from": 4, "densify_until": 12, "densify_every": 4,
                      "random_background": True})
    argv = ["--seed-ply", str(sc["seed"]), "--cameras", str(sc["cameras"]), "--images", str(sc["images"]),
            "--out", str(out), "--iterations", "16", "--test-cameras", str(sc["test_cameras"]),
            "--test-images", str(sc["test_images"]), "--image-list", str(tmp_path / "list.txt"),
            "--config", cfg, "--seed", "3", "--checkpoint-every", "8", "--eval-every", "8", "-q"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "test PSNR" in printed
    assert re.search(r"test PSNR: (\d+\.\d\d|n/a) ", printed), printed  # 2 decimals, not 16
    s = json.loads((out / "train.json").read_text())
    assert s["num_train_views"] == 3 and s["num_test_views"] == 2
    assert s["config"]["seed"] == 3 and s["config"]["random_background"] is True
    assert s["config"]["checkpoint_every"] == 8
    df = pq.read_table(out / "log.parquet").to_pandas()
    assert len(df) == 16 and df["test_psnr"].notna().sum() == 2
    assert {p.name for p in (out / "ckpt").iterdir()} == {"ckpt_0000008.pt", "ckpt_0000016.pt"}
    assert {p.name for p in (out / "renders").iterdir()} == {"view_01.png", "view_03.png"}

    # running again finds the final checkpoint and only rewrites the outputs
    assert main(argv) == 0
    assert json.loads((out / "train.json").read_text())["resumed_from"].endswith("ckpt_0000016.pt")

    # render: camera sizes from the images (PSNR logged), or an explicit size
    r1 = tmp_path / "r1"
    assert main(["render", "--model", str(out / "model.ply"), "--cameras", str(sc["test_cameras"]),
                 "--out", str(r1), "--images", str(sc["test_images"]), "-q"]) == 0
    img = read_image(r1 / "view_01.png")
    assert img.shape == (24, 32, 3)
    ref = read_image(out / "renders" / "view_01.png")
    assert np.abs(img - ref).max() <= 1 / 255 + 1e-6
    r2 = tmp_path / "r2"
    assert main(["render", "--model", str(out / "model.ply"), "--cameras", str(sc["test_cameras"]),
                 "--out", str(r2), "--width", "16", "--height", "12", "--background", "1,1,1", "-q"]) == 0
    assert read_image(r2 / "view_03.png").shape == (12, 16, 3)


def test_cli_reports_bad_input(tmp_path):
    sc = write_scene(tmp_path / "scene", n_views=2)
    with pytest.raises(ValueError, match="unknown training config keys"):
        main(["--seed-ply", str(sc["seed"]), "--cameras", str(sc["cameras"]), "--images", str(sc["images"]),
              "--out", str(tmp_path / "o"), "--config", '{"lr_nonsense": 1}'])
    with pytest.raises(KeyError, match="not in the camera model"):
        (tmp_path / "l.txt").write_text("missing.png\n")
        main(["--seed-ply", str(sc["seed"]), "--cameras", str(sc["cameras"]), "--images", str(sc["images"]),
              "--out", str(tmp_path / "o"), "--image-list", str(tmp_path / "l.txt"), "-q"])


@pytest.mark.parametrize("bad", ["gpu", "cuda:x", "cuda:-1", "cuda1"])
def test_a_device_that_names_no_device_is_one_line(tmp_path, bad):
    """--device takes auto, cpu, cuda or cuda:N; anything else is argparse's one line, exit 2,
    before anything is read or written."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "splat_train", "--seed-ply", "a.ply", "--cameras", "c",
                           "--images", "i", "--out", str(tmp_path / "o"), "--device", bad],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "is not a device" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()


def test_a_gpu_by_index_is_a_cuda_device(monkeypatch):
    """cuda:N names GPU N: a GPU device for the iteration default; with no GPU, or fewer than
    N + 1, the trainer says so in one sentence instead of a CUDA error."""
    from splat_train.config import PAPER_ITERATIONS, TrainConfig
    from splat_train.training.trainer import _device

    assert TrainConfig(device="cuda:1").iterations == PAPER_ITERATIONS
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(RuntimeError, match="'cuda:1' requested but torch sees no CUDA GPU"):
        _device("cuda:1")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(RuntimeError, match="sees 1 CUDA GPU"):
        _device("cuda:1")
    assert _device("cuda:0") == torch.device("cuda", 0)


def test_default_iterations_follow_the_device(monkeypatch):
    """A run that names no iteration count gets the paper's 10,000 where it trains on a GPU and
    1,000 on a CPU (where 10,000 take ~13 min for the fern n = 3 cell); the count is resolved
    when the config is made (checkpoints and the inputs digest hold the number), and an explicit
    --iterations or JSON value wins. The CLI's device flag decides, after the JSON config."""
    from splat_train.config import DEFAULT_ITERATIONS, PAPER_ITERATIONS, TrainConfig, load_config

    assert (DEFAULT_ITERATIONS, PAPER_ITERATIONS) == (1000, 10000)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert load_config(None).iterations == TrainConfig().iterations == 1000
    assert load_config(None, device="cuda").iterations == 10000
    assert load_config('{"device": "cuda"}', device="cpu").iterations == 1000  # the flag wins
    assert load_config('{"device": "cuda", "iterations": 30}').iterations == 30
    assert load_config(None, iterations=30, device="cuda").iterations == 30
    assert TrainConfig(device="cuda").to_dict()["iterations"] == 10000
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert load_config(None).iterations == 10000  # device auto on a CUDA machine
    with pytest.raises(ValueError, match="iterations must be an integer >= 1"):
        load_config(None, iterations=0)
    with pytest.raises(ValueError, match="unknown training config keys.*iteration"):
        load_config('{"iteration": 5}')
