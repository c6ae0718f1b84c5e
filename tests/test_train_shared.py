"""A short training run from a Bridge PLY on a real scene (LLFF fern from this project's
machine data, tests/_machine_data.py; skipped when absent): fern images_8 -> undistorted
prepared scene -> Bridge (COLMAP points) -> train."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from _machine_data import ABSENT, SCENES

FERN = SCENES / "llff__fern"
pytestmark = [pytest.mark.shared_data, pytest.mark.slow,
              pytest.mark.skipif(not FERN.is_dir(), reason=ABSENT)]


def test_train_from_bridge_ply_on_fern(tmp_path):
    from bridge.__main__ import main as bridge_main
    from camio.__main__ import main as camio_main
    from splat_train.__main__ import main as train_main

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene = tmp_path / "fern"
        assert camio_main(["-q", "convert", "--src", str(FERN), "--images-subdir", "images_8",
                           "--undistort", "--out", str(scene)]) == 0
        assert bridge_main(["--colmap", str(scene), "--images", str(scene / "images"),
                            "--out", str(tmp_path / "bridge"), "-q"]) == 0
        split = json.loads((scene / "split.json").read_text())
        (tmp_path / "train.txt").write_text("\n".join(split["train"]["3"]))
        (tmp_path / "test.txt").write_text("\n".join(split["test"]))
        cams = str(tmp_path / "bridge" / "sparse" / "0")
        out = tmp_path / "out"
        assert train_main(["--seed-ply", str(tmp_path / "bridge" / "seed.ply"), "--cameras", cams,
                           "--images", str(scene / "images"), "--image-list", str(tmp_path / "train.txt"),
                           "--test-cameras", cams, "--test-images", str(scene / "images"),
                           "--test-image-list", str(tmp_path / "test.txt"), "--downsample", "4",
                           "--iterations", "30", "--eval-every", "15", "--out", str(out), "-q"]) == 0
    finally:
        torch.set_num_threads(n)
    s = json.loads((out / "train.json").read_text())
    assert s["num_train_views"] == 3 and s["num_test_views"] == len(split["test"])
    assert np.isfinite(s["train_psnr"]) and np.isfinite(s["test_psnr"]) and s["test_psnr"] > 12  # measured 15.3 dB
    df = pq.read_table(out / "log.parquet").to_pandas()
    # the photometric L1 (the total adds binocular consistency from the densification start on)
    assert df["l1"].iloc[-5:].mean() < df["l1"].iloc[:5].mean()
    assert len(list((out / "renders").iterdir())) == len(split["test"])
