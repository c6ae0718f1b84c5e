"""Fault: every stage writes its outputs atomically (temporary name, then rename).

Two checks, both through :mod:`runtime.atomic`, the one place that renames:

* ``test_stage_writes_only_through_camio_atomic``: each stage runs with the final rename
  turned into a no-op that only records the destination. An output written through
  runtime.atomic then never appears (its temporary is removed); an output written directly
  would still be there. So after the stage, its output folder must hold no file at all,
  and the recorded destinations must be exactly the stage's outputs (docs/contracts.md).
* ``test_crash_at_rename_keeps_old_version``: each file writer crashes at the worst moment
  (temporary complete, rename not done, as a SIGKILL there would); the final path must still
  hold the previous complete version, and no temporary may be left under a final name.

A real SIGKILL mid-run is in tests/test_faults_resume.py.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

import runtime.atomic
from _train_scene import write_scene


class _NoRename:
    """Stands in for the ``os`` module inside runtime.atomic: ``replace`` into ``root`` records the
    destination and does nothing (or raises ``fail``); elsewhere it renames as usual."""

    def __init__(self, root: Path, fail: BaseException | None = None) -> None:
        self.root, self.fail, self.dests = root, fail, []

    def replace(self, src, dst):
        dst = Path(dst).resolve()
        if not dst.is_relative_to(self.root.resolve()):
            return os.replace(src, dst)  # the stage's inputs, prepared by the test itself
        if self.fail is not None:
            raise self.fail
        self.dests.append(dst.relative_to(self.root.resolve()).as_posix())

    def __getattr__(self, name):
        return getattr(os, name)


def _files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    from camio.synthetic import write_synthetic_scene

    return write_synthetic_scene(tmp_path_factory.mktemp("syn") / "scene", views=6, width=48, seed=0,
                                 n_gt_points=1500, n_ref_points=200, ns=(3,))


def _bridge(inp: Path, out: Path) -> None:
    from bridge.core import run_bridge
    from bridge.inputs import load_predictions
    from bridge.synthetic import write_synthetic_predictions

    run_bridge(load_predictions(write_synthetic_predictions(inp / "predictions.npz", n_views=3, height=8,
                                                            width=10)), out)


def _trainer(inp: Path, out: Path) -> None:
    from splat_train.config import TrainConfig
    from splat_train.training.trainer import train

    scene = write_scene(inp, n_views=3, width=16, height=12, n_test=1)
    n = torch.get_num_threads()
    try:
        train(scene["seed"], scene["cameras"], scene["images"], out,
              TrainConfig(iterations=4, checkpoint_every=2, eval_every=2, densify_until=0, device="cpu",
                          num_threads=1),
              test_cameras=scene["test_cameras"], test_images=scene["test_images"])
    finally:
        torch.set_num_threads(n)


def _vggt_export(inp: Path, out: Path) -> None:
    from bridge.synthetic import synthetic_predictions
    from vggt_init.export import PREDICTION_KEYS, OPTIONAL_KEYS, write_predictions

    arrays = synthetic_predictions(n_views=3, height=8, width=10)
    write_predictions(out / "predictions.npz",
                      {k: v for k, v in arrays.items() if k in PREDICTION_KEYS + OPTIONAL_KEYS})


def _oracle(scene: Path, out: Path) -> None:  # writes the vggt_init predictions schema
    from evaluation.initialisers.oracle import OracleNoise, run_oracle

    run_oracle(scene, ["0001.png", "0003.png", "0005.png"], out, OracleNoise(rot_deg=1.0), downsample=2)


def _colmap(scene: Path, out: Path) -> None:
    from evaluation.initialisers.colmap_baseline import run_colmap

    run_colmap(scene / "images", ["0001.png", "0003.png", "0005.png"], out)


def _pose(scene: Path, out: Path) -> None:
    from evaluation.metrics.pose import run_pose

    run_pose(scene / "sparse" / "0", scene / "sparse" / "0", out / "pose.json")


def _align(scene: Path, out: Path) -> None:
    from evaluation.metrics.align_run import run_align

    run_align(scene / "sparse" / "0", scene / "sparse" / "0", scene / "split.json", None, out, n=3)


def _metrics(scene: Path, out: Path) -> None:
    from evaluation.metrics.images_cli import evaluate_images

    evaluate_images(scene / "images", scene / "images", out / "metrics.json", lpips_nets=())


def _tables(tmp: Path, out: Path) -> None:
    from eval_fake_results import build
    from evaluation.reports.tables import run_tables

    results, _ = build(tmp)
    run_tables(results, out)


# stage -> (runner, input kind, the outputs it must have tried to rename into place);
# the oracle writes the vggt_init predictions.npz schema too
STAGES = {
    "bridge": (_bridge, "tmp", {"seed.ply", "sparse/0", "bridge.json"}),
    "splat_train": (_trainer, "tmp", {"ckpt/ckpt_0000002.pt", "ckpt/ckpt_0000004.pt", "log.parquet",
                                      "model.ply", "train.json", "renders/view_01.png"}),
    "vggt_init_export": (_vggt_export, "tmp", {"predictions.npz"}),
    "oracle_predictions": (_oracle, "scene", {"predictions.npz", "sparse/0", "status.json"}),
    "colmap_baseline": (_colmap, "scene", {"status.json"}),
    "eval_pose": (_pose, "scene", {"pose.json"}),
    "eval_align": (_align, "scene", {"align.json", "sparse/0"}),
    "eval_images": (_metrics, "scene", {"metrics.json"}),
    "eval_tables": (_tables, "tmp", {"runs.parquet", "tables.md"}),
}


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_stage_writes_only_through_camio_atomic(stage, tmp_path, monkeypatch, request):
    run, kind, expected = STAGES[stage]
    src = request.getfixturevalue("synth_scene") if kind == "scene" else tmp_path / "in"
    out = tmp_path / "out"
    out.mkdir()
    fake = _NoRename(out)
    monkeypatch.setattr(runtime.atomic, "os", fake)
    run(src, out)
    assert _files(out) == [], f"{stage} wrote these files without runtime.atomic"
    missing = expected - set(fake.dests)
    assert not missing, f"{stage} did not write {sorted(missing)} (recorded: {sorted(fake.dests)})"


def _cloud(n):
    from camio.ply import GaussianCloud

    rng = np.random.default_rng(n)
    return GaussianCloud.from_points(rng.normal(size=(n, 3)), rng.uniform(size=(n, 3)), np.full(n, 0.5),
                                     np.full(n, 0.1), sh_degree=3)


def _write_ply(p, v):
    from camio.ply import write_gaussian_ply

    write_gaussian_ply(p, _cloud(v))


def _read_ply(p):
    from camio.ply import read_gaussian_ply

    return len(read_gaussian_ply(p))


def _write_npz(p, v):
    runtime.atomic.save_npz(p, x=np.arange(v))


def _read_npz(p):
    with np.load(p) as z:
        return len(z["x"])


def _write_json(p, v):
    runtime.atomic.write_json(p, {"v": v})


def _write_ckpt(p, v):
    from splat_train.training.checkpoint import save_checkpoint

    save_checkpoint(p, 1, {"x": torch.arange(v)})


def _read_ckpt(p):
    from splat_train.training.checkpoint import load_checkpoint, latest_checkpoint

    return len(load_checkpoint(latest_checkpoint(p))["x"])


def _write_parquet(p, v):
    from splat_train.training.runlog import RunLog

    log = RunLog()
    for i in range(v):
        log.append(iteration=i + 1, wall_time_s=float(i), loss=1.0, l1=1.0, ssim=0.5, num_gaussians=1,
                   test_psnr=float("nan"), train_psnr=10.0)
    log.write_parquet(p)


def _read_parquet(p):
    import pyarrow.parquet as pq

    return pq.read_table(p).num_rows


def _write_model(p, v):
    from _train_scene import make_cameras
    from camio.colmap import write_text_model

    write_text_model(p, make_cameras(v))


def _read_model(p):
    from camio.colmap import read_model

    return len(read_model(p).cameras)


def _write_png(p, v):
    from camio.images import write_image

    write_image(p, np.full((4, v, 3), 0.5, np.float32))


def _read_png(p):
    from camio.images import image_size

    return image_size(p)[0]


# writer(path, v) writes a version identified by v; reader(path) gives v back
WRITERS = {
    "ply": ("seed.ply", _write_ply, _read_ply),
    "npz": ("predictions.npz", _write_npz, _read_npz),
    "json": ("x.json", _write_json, lambda p: json.loads(p.read_text())["v"]),
    "checkpoint": ("run", _write_ckpt, _read_ckpt),  # the run folder; the file is ckpt/ckpt_0000001.pt
    "parquet": ("log.parquet", _write_parquet, _read_parquet),
    "colmap_text": ("sparse/0", _write_model, _read_model),
    "png": ("r.png", _write_png, _read_png),
}


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_crash_at_rename_keeps_old_version(kind, tmp_path, monkeypatch):
    name, write, read = WRITERS[kind]
    path = tmp_path / name
    write(path, 3)
    assert read(path) == 3
    before = _files(tmp_path)
    monkeypatch.setattr(runtime.atomic, "os", _NoRename(tmp_path, fail=KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        write(path, 5)
    monkeypatch.undo()
    assert read(path) == 3, "the old complete version was lost"
    assert _files(tmp_path) == before, "a temporary was left behind"
