"""One benchmark cell (scene, n training views, seed), prepared once through the stage CLIs.

Scene conversion (or synthesis), the every-8th split, an initialiser from the scene's reference
cameras and the n training views (:data:`SEEDS`: ``posed``, points triangulated with them, by
default; ``mvs``, dense multi-view stereo; ``random``, 3DGS's random points), the Bridge (in a
mode for an initialiser with a confidence) and the alignment of the held-out cameras, each a
``python -m`` stage command (docs/contracts.md) whose output is kept: a second call finds the
files and runs nothing. The scene, split and name lists of a (scene, n) are shared by its seeds.

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
import re
from contextlib import contextmanager
from pathlib import Path

from experiments._proc import run_stage as sh
from experiments.sparse_views.protocol import Scene

#: the initialisers a cell seeds from: name -> (command, whether it writes a confidence)
SEEDS = {"posed": ("evaluation.initialisers.posed", False), "mvs": ("evaluation.initialisers.mvs", True),
         "random": ("evaluation.initialisers.random_init", False)}


def _flags(init_args: dict | None) -> list[str]:
    """An initialiser's extra flags from a variant's ``init_args`` ({"fill_stride": 0} ->
    ["--fill-stride", "0"]), in name order."""
    out = []
    for k, v in sorted((init_args or {}).items()):
        if not (isinstance(k, str) and re.fullmatch(r"[a-z][a-z0-9_]*", k)
                and isinstance(v, (int, float, str)) and re.fullmatch(r"[A-Za-z0-9.+-]+", str(v))):
            raise ValueError(f"init_args: a flag name and a plain value each (letters, digits, . + -), got {k!r}: {v!r}")
        out += [f"--{k.replace('_', '-')}", str(v)]
    return out


def seed_folder(init: str = "posed", mode: str | None = None, stride: int | None = None,
                init_args: dict | None = None) -> str:
    """The folder of a seed inside a cell: "" for ``posed`` (the cell itself, as before there
    was a choice), else ``seed_<init>[_<flag><value>...][_<mode>][_stride<K>]`` (``init_args``:
    the initialiser's flags other than its defaults; ``stride``: a Bridge pixel stride other
    than the Bridge's own)."""
    if init not in SEEDS:
        raise ValueError(f"unknown seed initialiser {init!r}; known: {', '.join(SEEDS)}")
    if mode is not None and not SEEDS[init][1]:
        raise ValueError(f"{init} has no confidence: no Bridge mode to choose (got {mode!r})")
    if stride is not None and (not SEEDS[init][1] or isinstance(stride, bool) or not isinstance(stride, int)
                               or stride < 1):
        raise ValueError(f"a Bridge stride is an integer >= 1 for an initialiser with a confidence "
                         f"({', '.join(k for k, v in SEEDS.items() if v[1])}); got {stride!r} for {init}")
    flags = _flags(init_args)
    if init == "posed":
        if flags:
            raise ValueError("the posed seed is the cell itself: it takes no init_args")
        return ""
    return (f"seed_{init}" + "".join(f"_{k}{v}" for k, v in sorted((init_args or {}).items()))
            + (f"_{mode}" if mode else "") + (f"_stride{stride}" if stride is not None else ""))


def prepare(work: Path, scene: Scene, n: int, init: str = "posed", mode: str | None = None,
            stride: int | None = None, init_args: dict | None = None) -> dict[str, Path]:
    """Prepare the cell of ``scene`` at ``n`` training views in ``work``, seeded by ``init``
    (:data:`SEEDS`; ``init_args`` its flags beyond its defaults; ``mode`` the Bridge mode of one
    with a confidence, the Bridge's default when None; ``stride`` its Bridge pixel stride, the
    Bridge's default when None); return its paths (scene, train / test name
    lists, bridge, align). Shards running side by side take turns (a lock file beside the cell)."""
    folder = seed_folder(init, mode, stride, init_args)
    with cell_lock(work):
        cell = _prepare(work, scene, n)
        if init == "posed":
            return cell
        return {**cell, **_seed(work, work / folder, init, mode, stride, init_args, cell, n)}


@contextmanager
def cell_lock(work: Path):
    """Hold the cell's lock (a file beside ``work``) so that shards running side by side take
    turns preparing it."""
    work.parent.mkdir(parents=True, exist_ok=True)
    with open(work.parent / f".{work.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _seed(work: Path, seed_dir: Path, init: str, mode: str | None, stride: int | None, init_args: dict | None,
          cell: dict, n: int) -> dict[str, Path]:
    """The initialiser ``init`` into ``work/seed_<init>[_<flags>]/init`` (run once, whichever
    Bridge mode reads it), then the Bridge and the alignment into ``seed_dir``."""
    s, logf = cell["scene"], work / "prepare.log"
    init_dir = work / seed_folder(init, init_args=init_args) / "init"
    if not (seed_dir / "bridge" / "bridge.json").is_file() and not (init_dir / "status.json").is_file():
        if init == "random":
            args = ["--cameras", str(s / "sparse" / "0")]
        else:
            args = ["--scene", str(s)]
        sh(["-m", SEEDS[init][0], *args, "--image-list", str(cell["train"]), "--out", str(init_dir),
            *_flags(init_args)], logf)
    return bridge_and_align(seed_dir, s, init_dir, n, logf, mode, stride)


def _prepare(work: Path, scene: Scene, n: int) -> dict[str, Path]:
    split = prepare_split(work, scene, n)
    s, logf, train_txt = split["scene"], work / "prepare.log", split["train"]
    init_dir = work / "posed"
    if not (work / "bridge" / "bridge.json").is_file():
        sh(["-m", "evaluation.initialisers.posed", "--scene", str(s), "--image-list", str(train_txt),
            "--out", str(init_dir)], logf)
    return {**split, **bridge_and_align(work, s, init_dir, n, logf)}


def prepare_split(work: Path, scene: Scene, n: int) -> dict[str, Path]:
    """The cell's scene (converted or generated into ``work/scene``) and its name lists
    ``work/train.txt`` (the split's ``n`` training views) and ``work/test.txt`` (the held-out
    views), each made once; returns {"scene", "train", "test"}. No seed, no training."""
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
    return {"scene": s, "train": train_txt, "test": test_txt}


def seed_model(init_dir: Path) -> Path:
    """The COLMAP model the cell seeds from: ``posed``'s triangulated model, or its random-point
    fallback model when the views triangulated no point at all (``status.json``; the workflow's
    rule, :func:`evaluation.initialisers.random_init.seed_model_dir`, with its benchmark switch)."""
    from evaluation.initialisers.random_init import seed_model_dir

    return seed_model_dir(init_dir, only_without_points=True)


def bridge_and_align(work: Path, scene: Path, init_dir: Path, n: int, log: Path,
                     mode: str | None = None, stride: int | None = None) -> dict[str, Path]:
    """The Bridge on an initialiser's output (its ``predictions.npz`` when it wrote one, in
    ``mode`` and with pixel ``stride`` when given, else its COLMAP model, :func:`seed_model`)
    into ``work/bridge``, then
    the held-out cameras aligned to it into ``work/align``; each skipped when its output
    exists. Returns {"bridge", "align"}."""
    bridge, align = work / "bridge", work / "align"
    if not (bridge / "bridge.json").is_file():
        if (init_dir / "predictions.npz").is_file():
            sh(["-m", "bridge", "--pred", str(init_dir / "predictions.npz"), "--out", str(bridge),
                *(["--mode", mode] if mode else []), *(["--stride", str(stride)] if stride else [])], log)
        else:
            sh(["-m", "bridge", "--colmap", str(seed_model(init_dir)), "--images", str(scene / "images"),
                "--out", str(bridge)], log)
    if not (align / "align.json").is_file():
        sh(["-m", "evaluation", "align", "--pred", str(bridge / "sparse" / "0"), "--ref",
            str(scene / "sparse" / "0"), "--train-names", str(scene / "split.json"), "--n", str(n), "--images",
            str(scene / "images"), "--out", str(align)], log)
    return {"bridge": bridge, "align": align}
