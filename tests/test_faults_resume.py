"""Fault: a training job SIGKILLed mid-run resumes from its last checkpoint and ends with the
same model, bit for bit, as an uninterrupted run with the same seed (CPU, one thread).

The killed job is a real process, ``python -m splat_train`` on a tiny generated scene
(tests/_train_scene.py), killed with SIGKILL (no clean-up code runs) as soon as its first
checkpoint file appears. The uninterrupted reference and the resumed run use the same
configuration in this process (what the CLI calls: ``load_config`` then ``train``; one thread
both here and in the child), which saves two interpreter start-ups.
The kill also checks atomic writes: every checkpoint left behind must load, and no
model.ply / train.json may exist (they are written only at the end).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from _train_scene import write_scene
from camio.ply import read_gaussian_ply
from splat_train.checkpoint import list_checkpoints, load_checkpoint

pytestmark = pytest.mark.slow

ITERATIONS = 120
CKPT_EVERY = 20
# densification, an opacity reset and SH increases all happen before and after the kill
CONFIG = {"densify_from": 5, "densify_until": 80, "densify_every": 20, "opacity_reset_every": 50,
          "sh_increase_every": 30, "scale_schedule": False, "keep_checkpoints": 2}


def _command(scene: dict, out: Path) -> list[str]:
    return [sys.executable, "-m", "splat_train", "--seed", str(scene["seed"]), "--cameras",
            str(scene["cameras"]), "--images", str(scene["images"]), "--out", str(out),
            "--iterations", str(ITERATIONS), "--checkpoint-every", str(CKPT_EVERY), "--seed-rng", "7",
            "--device", "cpu", "--threads", "1", "--config", json.dumps(CONFIG), "-q"]


def _env() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _run(scene: dict, out: Path) -> None:
    """What ``python -m splat_train <_command args>`` does, in this process."""
    from splat_train.config import load_config
    from splat_train.trainer import train

    cfg = load_config(json.dumps(CONFIG), iterations=ITERATIONS, downsample=None, seed=7,
                      checkpoint_every=CKPT_EVERY, eval_every=None, pose_refine=None, device="cpu",
                      num_threads=1)
    n = torch.get_num_threads()
    try:
        train(scene["seed"], scene["cameras"], scene["images"], out, cfg)
    finally:
        torch.set_num_threads(n)


def _kill_after_first_checkpoint(scene: dict, out: Path) -> None:
    log = open(out.parent / f"{out.name}.log", "w")
    proc = subprocess.Popen(_command(scene, out), env=_env(), stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 240
        while not list_checkpoints(out):
            assert proc.poll() is None, f"training exited ({proc.returncode}) before its first checkpoint"
            assert time.monotonic() < deadline, "no checkpoint after 240 s"
            time.sleep(0.002)
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()


def test_sigkilled_training_resumes_to_identical_model(tmp_path):
    scene = write_scene(tmp_path / "scene", n_views=4)
    full, killed = tmp_path / "full", tmp_path / "killed"
    _run(scene, full)

    _kill_after_first_checkpoint(scene, killed)
    left = list_checkpoints(killed)
    assert left and left[-1][0] < ITERATIONS, "the run was not interrupted"
    for _, path in left:  # atomic: whatever is there under a final name is complete
        assert load_checkpoint(path)["iteration"] % CKPT_EVERY == 0
    assert not (killed / "model.ply").exists() and not (killed / "train.json").exists()
    last = left[-1][1]

    _run(scene, killed)  # same command: resumes from ckpt/
    summary = json.loads((killed / "train.json").read_text())
    assert summary["resumed_from"] == str(last)

    a, b = read_gaussian_ply(full / "model.ply"), read_gaussian_ply(killed / "model.ply")
    assert len(a) == len(b)
    for key in ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    la, lb = (pq.read_table(d / "log.parquet").to_pandas() for d in (full, killed))
    assert list(lb["iteration"]) == list(range(1, ITERATIONS + 1))  # no gap, no duplicate
    np.testing.assert_array_equal(la["loss"].to_numpy(), lb["loss"].to_numpy())
    np.testing.assert_array_equal(la["num_gaussians"].to_numpy(), lb["num_gaussians"].to_numpy())
