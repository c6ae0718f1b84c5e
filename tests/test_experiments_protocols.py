"""experiments/protocols.py: the recovery check's known camera error and the summary table."""

from __future__ import annotations

import math

import numpy as np
import pytest

from experiments import protocols
from splat_train.testpose import pose_change


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_perturb_moves_the_camera_by_the_stated_error(seed):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    pose = np.concatenate([R, rng.normal(size=(3, 1))], 1)
    depth = 3.7
    moved = protocols._perturb(pose, depth, np.random.default_rng(seed))
    rot_deg, centre_shift = pose_change(pose, moved)
    assert rot_deg == pytest.approx(protocols.PERTURB_DEG, abs=1e-9)
    # the shift is applied in the camera frame after the rotation: |t| in the moved frame, and the
    # camera centre moves by R'^T t plus the rotation's swing of the old centre about the origin
    t = moved[:, 3] - moved[:, :3] @ pose[:, :3].T @ pose[:, 3]
    assert np.linalg.norm(t) == pytest.approx(protocols.PERTURB_FRAC * depth, rel=1e-9)
    assert math.isfinite(centre_shift)


def test_table_has_both_protocols_in_its_headers():
    report = {"prepared": {"scene": "llff/fern", "n": 3}, "device": "cpu", "iterations": 10, "testpose_steps": 5,
              "cells": {"posed": {"train": {"num_gaussians": 5}, "strict": {"psnr": 12.0, "ssim": 0.3},
                                  "test-pose": {"psnr": 14.5, "ssim": 0.4}, "testpose_record": {"mean_rotation_deg": 0.5},
                                  "train_s": 3.0, "testpose_s": 1.0},
                        "colmap": {"error": "RuntimeError: boom"}}}
    md = protocols.table(report)
    assert "PSNR [strict]" in md and "PSNR [test-pose]" in md
    assert "| posed | 5 | 12.00 | 0.300 | 14.50 | 0.400 |" in md
    assert "error: RuntimeError: boom" in md


def test_bad_folders_are_one_line_and_exit_2(tmp_path, capsys):
    assert protocols.main(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "out")]) == 2
    assert "not a folder made by `protocols.py prepare`" in capsys.readouterr().err
    (tmp_path / "prep").mkdir()
    (tmp_path / "prep" / "prepared.json").write_text("{}")
    assert protocols.main(["run", str(tmp_path / "prep"), "--out", str(tmp_path / "prep" / "out")]) == 2
    assert "overlaps the prepared folder" in capsys.readouterr().err
    assert not (tmp_path / "prep" / "out").exists()
    assert protocols.main(["prepare", str(tmp_path / "prep")]) == 2  # exists: refused, nothing run
    assert "exists" in capsys.readouterr().err
