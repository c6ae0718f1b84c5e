"""Training results pinned bit for bit: every recipe, trained a few dozen iterations on the tiny
generated scene, ends with exactly the parameters, log, schedule, train.json ``config`` and
inputs digest recorded in ``tests/data/train_golden.json``; a committed checkpoint
(``tests/data/train_golden_ckpt/``, its config a flat dict as every checkpoint holds) resumes to
the same end.

The record is regenerated with ``python tests/test_train_golden.py`` (only where a change of the
training result is intended; the diff of the JSON file then shows what moved).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _train_scene import write_scene  # noqa: E402

GOLDEN = Path(__file__).resolve().parent / "data" / "train_golden.json"
OLD_CKPT = Path(__file__).resolve().parent / "data" / "train_golden_ckpt"

BASE = dict(iterations=40, device="cpu", checkpoint_every=20, keep_checkpoints=5, eval_every=20)
# name -> the flat config keys of the run (the recipes as they are, and user keys over them)
CASES = {
    "paper": dict(recipe="paper"),
    "dropgaussian": dict(recipe="dropgaussian"),
    "sparse": dict(recipe="sparse"),
    "mcmc": dict(recipe="mcmc"),
    # the variants that keep a recipe's earlier values (splat_train.recipes.VARIANTS): each ends
    # where its recipe ended before the recipe changed (its runs' records are kept under it)
    "paper-seedcode": dict(recipe="paper-seedcode"),
    "dropgaussian-wsprune": dict(recipe="dropgaussian-wsprune"),
    "mcmc-keep": dict(recipe="mcmc-keep"),
    # a part's value under a recipe without it turns the part on; a set schedule key is kept
    "paper+dropout+pose": dict(recipe="paper", dropout_rate=0.1, densify_every=15, pose_refine=True,
                               pose_refine_from=5, pose_warmup=5, lr_pose=1e-3),
    # the densification of the default strategy within the run (a set period)
    "dropgaussian+densify": dict(recipe="dropgaussian", densify_every=10),
    "sparse+densify": dict(recipe="sparse", densify_every=10, opacity_reset_every=30),
    # a part's off value turns the recipe's part off; a fixed background
    "sparse-off": dict(recipe="sparse", binocular_weight=0.0, opacity_decay=1.0, dropout_rate=0.0,
                       background=[0.2, 0.3, 0.4], random_background=False),
}


def write_golden_scene(root: Path) -> dict[str, Path]:
    """The scene of the record: 4 training and 2 test views of 32 x 24, and a depth prior beside
    the seed (random samples, so that the sparse recipe's depth term acts)."""
    from camio.depth_prior import DEPTH_PRIOR_FILE, DepthSamples, write_depth_prior

    paths = write_scene(root, n_views=4, n_test=2)
    names = sorted(p.name for p in paths["images"].iterdir())
    g = np.random.default_rng(3)
    n = 40 * len(names)
    s = DepthSamples(names, [[32, 24]] * len(names), np.repeat(np.arange(len(names)), 40),
                     np.c_[g.uniform(0, 32, n), g.uniform(0, 24, n)], g.uniform(2.0, 4.0, n),
                     g.uniform(0.2, 1.0, n), "dense")
    write_depth_prior(paths["seed"].parent / DEPTH_PRIOR_FILE, s)
    return paths


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_case(scene: dict[str, Path], out: Path, keys: dict) -> dict:
    """Train one case through the config loader the CLI uses; the record of its end."""
    import pyarrow.parquet as pq

    from splat_train.config import load_config
    from splat_train.training.trainer import train

    cfg = load_config({**BASE, **keys})
    res = train(scene["seed"], scene["cameras"], scene["images"], out, cfg,
                test_cameras=scene["test_cameras"], test_images=scene["test_images"])
    s = res.summary
    table = pq.read_table(out / "log.parquet").to_pydict()
    return {
        "model_ply_sha256": _digest(out / "model.ply"),
        "num_gaussians": s["num_gaussians"],
        "loss": table["loss"],
        "test_psnr": [x for x in table["test_psnr"] if x == x],
        "schedule": s["schedule"],
        "inputs_sha256": s["inputs_sha256"],
        "config": s["config"],
        "strategy": s["strategy"],
        "max_gaussians": s["max_gaussians"],
        "strategy_totals": s["strategy_totals"],
        "background_from": s["background_from"],
        "summary_keys": sorted(s),
    }


@pytest.fixture(scope="module")
def golden_scene(tmp_path_factory, one_thread):
    return write_golden_scene(tmp_path_factory.mktemp("golden"))


@pytest.fixture(scope="module")
def golden():
    return json.loads(GOLDEN.read_text())


@pytest.mark.parametrize("case", sorted(CASES))
def test_training_is_bit_identical_to_the_record(case, golden_scene, golden, tmp_path):
    got = json.loads(json.dumps(run_case(golden_scene, tmp_path / case, CASES[case])))
    want = golden[case]
    for key in want:
        assert got[key] == want[key], (case, key)


def test_an_old_checkpoint_resumes_to_the_recorded_end(golden_scene, golden, tmp_path):
    """The committed checkpoint (iteration 20 of the ``sparse`` case) resumes and ends bit for bit
    where the uninterrupted run ends."""
    out = tmp_path / "resumed"
    shutil.copytree(OLD_CKPT, out / "ckpt")
    got = run_case(golden_scene, out, CASES["sparse"])
    assert str(got.get("model_ply_sha256")) == golden["sparse"]["model_ply_sha256"]
    assert got["loss"] == golden["sparse"]["loss"]
    resumed = json.loads((out / "train.json").read_text())["resumed_from"]
    assert resumed is not None and resumed.endswith("ckpt_0000020.pt")


def main() -> None:
    """Regenerate the record and the old-format checkpoint fixture."""
    import tempfile

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = write_golden_scene(tmp / "scene")
        record = {}
        for case, keys in sorted(CASES.items()):
            record[case] = run_case(scene, tmp / case, keys)
            print(case, record[case]["model_ply_sha256"][:16], record[case]["num_gaussians"])
        GOLDEN.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
        if "--checkpoint" in sys.argv:
            shutil.rmtree(OLD_CKPT, ignore_errors=True)
            OLD_CKPT.mkdir(parents=True)
            shutil.copy(tmp / "sparse" / "ckpt" / "ckpt_0000020.pt", OLD_CKPT)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    main()
