"""Fault: a training job SIGKILLed mid-run resumes from its last checkpoint and ends with the
same model, bit for bit, as an uninterrupted run with the same seed (CPU, one thread).

The killed job is a real process, ``python -m splat_train`` on a tiny generated scene
(tests/_train_scene.py), killed with SIGKILL (no clean-up code runs) as soon as its first
checkpoint file appears. The uninterrupted reference and the resumed run use the same
configuration in this process (what the CLI calls: ``load_config`` then ``train``; one thread
both here and in the child), which saves two interpreter start-ups.
The kill also checks atomic writes: every checkpoint left behind must load, and no
model.ply / train.json may exist (they are written only at the end).

The workflow's ``train_splats`` rule is killed the same way (snakemake and its job, SIGKILL)
and rerun: it resumes from the checkpoint it keeps in ``train_resume/``, outside its outputs.
"""

from __future__ import annotations

import json
import os
import re
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
from splat_train.training.checkpoint import list_checkpoints, load_checkpoint

pytestmark = pytest.mark.slow

ITERATIONS = 120
CKPT_EVERY = 20
# densification, an opacity reset and SH increases all happen before and after the kill
CONFIG = {"densify_from": 5, "densify_until": 80, "densify_every": 20, "opacity_reset_every": 50,
          "sh_increase_every": 30, "keep_checkpoints": 2}


def _command(scene: dict, out: Path) -> list[str]:
    return [sys.executable, "-m", "splat_train", "--seed-ply", str(scene["seed"]), "--cameras",
            str(scene["cameras"]), "--images", str(scene["images"]), "--out", str(out),
            "--iterations", str(ITERATIONS), "--checkpoint-every", str(CKPT_EVERY), "--seed", "7",
            "--device", "cpu", "--threads", "1", "--config", json.dumps(CONFIG), "-q"]


def _env() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _run(scene: dict, out: Path) -> None:
    """What ``python -m splat_train <_command args>`` does, in this process."""
    from splat_train.config import load_config
    from splat_train.training.trainer import train

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


# ----------------------------------------------------------------------------- the workflow rule

REPO = Path(__file__).resolve().parents[1]
RULE_ITERATIONS, RULE_CKPT_EVERY = 300, 10


def _workflow_config(tmp_path: Path) -> Path:
    """.test/config.yaml cut to one training run (oracle, 3 views), checkpointing often."""
    import yaml

    cfg = yaml.safe_load((REPO / ".test" / "config.yaml").read_text())
    cfg.update(results="results", views=[3], initialisers=["oracle"])
    cfg["vggt"].update(checkpoint=str(REPO / cfg["vggt"]["checkpoint"]),
                       model_config=str(REPO / cfg["vggt"]["model_config"]))
    cfg["train"].update(iterations=RULE_ITERATIONS, checkpoint_every=RULE_CKPT_EVERY, threads=1)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _snakemake_cmd(tmp_path: Path, target: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "snakemake", target, "--cores", "1", "--snakefile", str(REPO / "Snakefile"),
            "--directory", str(tmp_path), "--configfile", str(tmp_path / "config.yaml"), *extra]


def test_killed_train_splats_rule_resumes_from_its_checkpoint(tmp_path):
    """The real rule: SIGKILL snakemake and its training job (a node lost) once a checkpoint is
    in train_resume/, rerun the rule: it resumes from iteration k > 0 (same inputs: hash checked)
    and its model equals an uninterrupted run of the same command, bit for bit (one thread)."""
    pytest.importorskip("snakemake")
    _workflow_config(tmp_path)
    run = tmp_path / "results" / "ci" / "tiny" / "n3" / "oracle" / "gated"
    target = str(run.relative_to(tmp_path) / "train" / "model.ply")
    env = {**_env(), "PYTHONPATH": str(REPO)}
    log = open(tmp_path / "snakemake_killed.log", "w")
    proc = subprocess.Popen(_snakemake_cmd(tmp_path, target), env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    resume = run / "train_resume"
    try:
        deadline = time.monotonic() + 600
        while not list(resume.glob("*/ckpt/ckpt_*.pt")):
            assert proc.poll() is None, (tmp_path / "snakemake_killed.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "no training checkpoint after 600 s"
            time.sleep(0.002)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()
        log.close()
    assert not (run / "train" / "train.json").exists(), "training finished before the kill"
    (ckpt_dir,) = resume.glob("*/ckpt")
    killed_at = max(i for i, _ in list_checkpoints(ckpt_dir.parent))
    assert 0 < killed_at < RULE_ITERATIONS

    subprocess.run(_snakemake_cmd(tmp_path, target, "--unlock"), env=env, check=True, capture_output=True)
    rerun = subprocess.run(_snakemake_cmd(tmp_path, target, "--rerun-incomplete"), env=env,
                           capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, (rerun.stdout + rerun.stderr)[-4000:]
    train_log = (run / "logs" / "train.log").read_text()
    resumed = re.search(r"resumed from \S+ at iteration (\d+)", train_log)
    assert resumed and int(resumed.group(1)) >= killed_at > 0, train_log[-2000:]
    summary = json.loads((run / "train" / "train.json").read_text())
    assert summary["resumed_from"] and summary["inputs_sha256"].startswith(ckpt_dir.parent.name)
    assert not resume.exists(), "the checkpoints of a finished run were left behind"

    # the uninterrupted reference: the rule's own command into another folder (from -p)
    dry = subprocess.run(_snakemake_cmd(tmp_path, target, "-n", "-p", "--forcerun", "train_splats"), env=env,
                         capture_output=True, text=True, timeout=300, check=True)
    cmd = re.search(r"^(?:Shell command: )?(python -m splat_train .*)$", dry.stdout + dry.stderr, re.M).group(1)
    cmd = cmd.split(" > ")[0].replace(str(run.relative_to(tmp_path) / "train_resume"),
                                      str(tmp_path / "ref_resume"))
    cmd = cmd.replace(f"--out {run.relative_to(tmp_path)}/train", f"--out {tmp_path / 'ref'}")
    subprocess.run(cmd, shell=True, cwd=tmp_path, env=env, check=True, capture_output=True, timeout=600)
    a, b = read_gaussian_ply(tmp_path / "ref" / "model.ply"), read_gaussian_ply(run / "train" / "model.ply")
    assert len(a) == len(b)
    for key in ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)


def test_resume_dir_is_keyed_by_the_inputs_hash(tmp_path):
    """--resume-dir: checkpoints under RES/<hash>/ckpt, another hash's checkpoint folder is
    stale and removed (a user's files there are left alone), RES goes once empty; a checkpoint of other inputs in OUT/ckpt
    is refused, naming the hash."""
    from splat_train.config import load_config
    from splat_train.data import load_views
    from splat_train.training.trainer import inputs_digest, train

    scene = write_scene(tmp_path / "scene", n_views=3)
    cfg = load_config(None, iterations=6, downsample=None, seed=0, checkpoint_every=3, eval_every=None,
                      pose_refine=None, device="cpu", num_threads=1)
    views = load_views(scene["cameras"], scene["images"], None, cfg.downsample, (0.0, 0.0, 0.0))  # opaque images
    digest = inputs_digest(scene["seed"], views, cfg)
    assert digest == inputs_digest(scene["seed"], views, cfg)
    assert digest != inputs_digest(scene["seed"], views, load_config(None, iterations=7, device="cpu"))

    res = tmp_path / "res"
    (res / "0123456789abcdef" / "ckpt").mkdir(parents=True)  # another run's, stale
    (res / "notes.txt").write_text("a user's file")  # not the trainer's: never deleted
    (res / "fedcba9876543210").mkdir()
    (res / "fedcba9876543210" / "data.bin").write_bytes(b"x")  # a digest-like name, not a checkpoint folder
    n = torch.get_num_threads()
    try:
        out = train(scene["seed"], scene["cameras"], scene["images"], tmp_path / "out", cfg, resume_dir=res)
        assert out.summary["inputs_sha256"] == digest
        assert sorted(p.name for p in res.iterdir()) == ["fedcba9876543210", "notes.txt"]

        # a checkpoint of these inputs, then the seed changes: refused
        train(scene["seed"], scene["cameras"], scene["images"], tmp_path / "out2", cfg)
        seed = read_gaussian_ply(scene["seed"])
        seed.means[0, 0] += 1e-3
        from camio.ply import write_gaussian_ply

        write_gaussian_ply(scene["seed"], seed)
        (tmp_path / "out2" / "model.ply").unlink()
        with pytest.raises(ValueError, match="other inputs"):
            train(scene["seed"], scene["cameras"], scene["images"], tmp_path / "out2", cfg)
    finally:
        torch.set_num_threads(n)
