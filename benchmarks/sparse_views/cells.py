"""One benchmark cell (scene, n training views), prepared once through the stage CLIs.

Scene conversion (or synthesis), the every-8th split, the ``posed`` initialiser (reference
cameras, points triangulated from the n training views), the Bridge and the alignment of the
held-out cameras, each a ``python -m`` stage command (docs/contracts.md) whose output is kept:
a second call finds the files and runs nothing.

The seed is the triangulated points alone, however few: unlike the workflow, the cell does not
switch to ``posed``'s random-point fallback (``evaluation.initialisers.random_init``) below 100
points, so every recipe starts from the same measured geometry (at the benchmark's image sizes
most scenes triangulate 12-95 points from 3 views, fern 188). Only a cell whose views
triangulate no point at all (three views around an object share too little) seeds from that
fallback, 3DGS's random initialisation, as the workflow would (:func:`seed_model`).
"""

from __future__ import annotations

import fcntl
import json
from pathlib import Path

from benchmarks._proc import run_stage as sh
from benchmarks.sparse_views.protocol import Scene


def prepare(work: Path, scene: Scene, n: int) -> dict[str, Path]:
    """Prepare the cell of ``scene`` at ``n`` training views in ``work``; return its paths
    (scene, train / test name lists, bridge, align). Shards running side by side take turns
    (a lock file beside the cell)."""
    work.parent.mkdir(parents=True, exist_ok=True)
    with open(work.parent / f".{work.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return _prepare(work, scene, n)


def _prepare(work: Path, scene: Scene, n: int) -> dict[str, Path]:
    s, logf = work / "scene", work / "prepare.log"
    if not (s / "split.json").is_file():
        if scene.generate:
            cmd = [str(s) if a == "{out}" else a for a in scene.generate]
            if cmd[:2] != ["python", "-m"]:
                raise ValueError(f"{scene.name}: 'generate' must be a 'python -m ...' command, got {cmd}")
            sh(cmd[1:], logf)
        else:
            sh(["-m", "camio", "convert", "--src", str(scene.path), *scene.convert, "--out", str(s)], logf)
        sh(["-m", "camio", "split", "--scene", str(s), "--n", str(n), "--out", str(s / "split.json")], logf)
    train_txt, test_txt = work / "train.txt", work / "test.txt"
    if not train_txt.is_file():
        split = json.loads((s / "split.json").read_text())
        if str(n) not in split.get("train", {}):
            raise ValueError(f"{scene.name}: the split has no n = {n} (pool of {len(split['train_pool'])})")
        test_txt.write_text("\n".join(split["test"]) + "\n")
        train_txt.write_text("\n".join(split["train"][str(n)]) + "\n")
    init_dir = work / "posed"
    if not (work / "bridge" / "bridge.json").is_file():
        sh(["-m", "evaluation.initialisers.posed", "--scene", str(s), "--image-list", str(train_txt),
            "--out", str(init_dir)], logf)
    return {"scene": s, "train": train_txt, "test": test_txt, **bridge_and_align(work, s, init_dir, n, logf)}


def seed_model(init_dir: Path) -> Path:
    """The COLMAP model the cell seeds from: ``posed``'s triangulated model, or its random-point
    fallback model when the views triangulated no point at all (``status.json``; the workflow's
    rule, :func:`evaluation.initialisers.random_init.seed_model_dir`, with its benchmark switch)."""
    from evaluation.initialisers.random_init import seed_model_dir

    return seed_model_dir(init_dir, only_without_points=True)


def bridge_and_align(work: Path, scene: Path, init_dir: Path, n: int, log: Path) -> dict[str, Path]:
    """The Bridge on an initialiser's output (its ``predictions.npz`` when it wrote one, else its
    COLMAP model, :func:`seed_model`) into ``work/bridge``, then the held-out cameras aligned to
    it into ``work/align``; each skipped when its output exists. Returns {"bridge", "align"}."""
    bridge, align = work / "bridge", work / "align"
    if not (bridge / "bridge.json").is_file():
        if (init_dir / "predictions.npz").is_file():
            sh(["-m", "bridge", "--pred", str(init_dir / "predictions.npz"), "--out", str(bridge)], log)
        else:
            sh(["-m", "bridge", "--colmap", str(seed_model(init_dir)), "--images", str(scene / "images"),
                "--out", str(bridge)], log)
    if not (align / "align.json").is_file():
        sh(["-m", "evaluation", "align", "--pred", str(bridge / "sparse" / "0"), "--ref",
            str(scene / "sparse" / "0"), "--train-names", str(scene / "split.json"), "--n", str(n), "--images",
            str(scene / "images"), "--out", str(align)], log)
    return {"bridge": bridge, "align": align}
