"""One benchmark run: train a recipe on a prepared cell, score its final model, write one record.

Training is ``python -m splat_train`` with the held-out curve (PSNR, SSIM along the run);
the final model is rendered into the aligned held-out cameras (``python -m splat_train
render``) and scored by ``python -m evaluation images`` (PSNR, SSIM, LPIPS-Alex, LPIPS-VGG),
the same commands the workflow runs. The record holds the keys of the results table
(:data:`RECORD_KEYS`) and the held-out curve.

A run is found again by its name (scene, n, recipe, seed, iterations), so a recipe whose values
changed since would silently reuse the old model and record. Every record therefore keeps the
values its run resolved (``values``: the recipe's parts, thresholds and schedule in
iterations, :func:`resolved_values`); a kept model or record whose values differ from what the
recipe gives now stops the run with :class:`StaleRun`, naming the keys and the path to remove.
"""

from __future__ import annotations

import fcntl
import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from experiments._proc import run_stage as sh
from splat_train.recipes import BACKGROUND_BLACK, BACKGROUND_MEAN, BINOCULAR_FROM_FRACTION, PRUNE_WORLD_SIZE_3DGS


@contextmanager
def run_lock(lock: Path) -> Iterator[bool]:
    """Hold the lock of one run while the block runs, so that two ``run`` commands over
    overlapping grids never train the same run at once: yields False, holding nothing, when
    another process holds it. An advisory lock on an open file (``flock``): the system drops it
    when its process ends, however it ends, so a killed run never blocks the next command."""
    lock = Path(lock)
    lock.parent.mkdir(parents=True, exist_ok=True)
    with open(lock, "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


class StaleRun(ValueError):
    """A kept model or record was made with other recipe values than the recipe gives now."""


def resolved_values(recipe: str, overrides: dict, iterations: int) -> dict:
    """What a run of ``recipe`` with config ``overrides`` resolves to: the recipe-set values
    (regularisation parts, densification thresholds, strategy) and the schedule in iterations."""
    from splat_train.config import load_config
    from splat_train.recipes import PART_KEYS, RAMP_KEYS, VALUE_KEYS

    cfg = load_config({"recipe": recipe, **overrides}, iterations=iterations, device="cpu")
    out = {k: getattr(cfg, k) for k in (*PART_KEYS, *RAMP_KEYS, *VALUE_KEYS)}
    sched = cfg.schedule().to_dict()
    sched.pop("source", None)
    return {**out, **sched}


#: a variant's config keys that choose its seed (experiments.sparse_views.cells.prepare), not training values
SEED_KEYS = ("init", "init_args", "bridge_mode", "bridge_stride")


# Values that became keys after records were made, with the value every run had before: a
# record without the key ran with it.
IMPLIED_VALUES = {"dropout_ramp_fraction": 1.0, "binocular_weight": 0.0,
                  "binocular_from_fraction": BINOCULAR_FROM_FRACTION, "opacity_decay": 1.0,
                  "mcmc_growth": "gsplat", "background": list(BACKGROUND_BLACK),
                  "prune_world_size": PRUNE_WORLD_SIZE_3DGS}


def stale_keys(found: dict, want: dict) -> list[str]:
    """The keys of ``want`` whose value in ``found`` differs (numbers compared as floats; a key
    of :data:`IMPLIED_VALUES` that ``found`` predates counts at its implied value)."""
    def same(a, b) -> bool:
        if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
            return float(a) == float(b)
        return a == b
    found = {**IMPLIED_VALUES, **found}
    return sorted(k for k, v in want.items() if k not in found or not same(found[k], v))


def train_values(tj: dict) -> dict:
    """The values a finished run resolved, read from its train.json (config + schedule); its
    ``background`` as asked: "mean" where the trainer resolved the training images' mean colour
    (train.json's ``background_from``; a run that predates the key counts as the colour set)."""
    out = {**(tj.get("config") or {}), **(tj.get("schedule") or {})}
    if tj.get("background_from") == BACKGROUND_MEAN:
        out["background"] = BACKGROUND_MEAN
    return out


RECORD_KEYS = ("scene", "role", "n", "recipe", "seed", "iterations", "psnr", "ssim", "lpips_alex", "lpips_vgg",
               "gaussians", "train_s", "backend")


def run_name(scene: str, n: int, recipe: str, seed: int, iterations: int) -> str:
    return f"{scene}_n{n}_{recipe}_s{seed}_i{iterations}"


def train_args(cell: dict[str, Path], out: Path, recipe: str, seed: int, iterations: int, eval_every: int,
               config: dict | None = None, kernel_threads: int = 0) -> list[str]:
    """The ``python -m splat_train`` arguments of one grid run (without ``-m splat_train``):
    ``recipe`` plus ``config`` overrides on ``cell``, into ``out``, the held-out curve every
    ``eval_every`` iterations."""
    cfg = {"recipe": recipe, **(config or {})}
    return ["--seed-ply", str(cell["bridge"] / "seed.ply"), "--cameras", str(cell["bridge"]),
            "--images", str(cell["scene"] / "images"), "--image-list", str(cell["train"]),
            "--test-cameras", str(cell["align"]), "--test-images", str(cell["scene"] / "images"),
            "--test-image-list", str(cell["test"]), "--out", str(out), "--iterations", str(iterations),
            "--seed", str(seed), "--eval-every", str(eval_every), "--checkpoint-every", str(iterations),
            "--kernel-threads", str(kernel_threads), "--config", json.dumps(cfg)]


def train_and_score(cell: dict[str, Path], out: Path, recipe: str, seed: int, iterations: int,
                    eval_every: int, config: dict | None = None, kernel_threads: int = 0,
                    extra_args: tuple[str, ...] = (), score: bool = True) -> dict:
    """Train ``recipe`` (plus ``config`` overrides) on ``cell`` into ``out`` unless its train.json
    exists, then score the final model unless its metrics.json exists; return the measures.
    The held-out renders use the background the run trained against too (a colour the config
    sets, "mean" as train.json's config resolved it, explicitly; else the renderer's default,
    the model's train.json colour), returned as ``background`` (train.json's; None where it
    keeps none). ``extra_args``: more ``python -m splat_train`` arguments
    (the GPU check's ``--device cuda --rasterizer gsplat``); ``score=False``: training only
    (``metrics`` None; the held-out curve in train.json still has the final iteration's PSNR
    and SSIM)."""
    logf = out.parent / f"{out.name}.log"
    want = resolved_values(recipe, config or {}, iterations)
    if (out / "train.json").is_file():
        bad = stale_keys(train_values(json.loads((out / "train.json").read_text())), want)
        if bad:
            raise StaleRun(f"{out} was trained with other values of {', '.join(bad)} than recipe {recipe!r} "
                           f"gives now: remove the folder to train it again")
    else:
        sh(["-m", "splat_train", *train_args(cell, out, recipe, seed, iterations, eval_every, config, kernel_threads),
            *extra_args], logf)
    tj = json.loads((out / "train.json").read_text())
    trained = tj.get("config", {}).get("background")  # the colour it trained against ("mean" resolved)
    # the renders: a set colour explicitly, else the renderer's default, the model's train.json colour
    bg = None if (config or {}).get("background") is None else trained
    if not score:
        return {"train": tj, "metrics": None, "values": want, "background": trained}
    metrics = out / "final" / "metrics.json"
    if not metrics.is_file():
        renders, gt = out / "final" / "renders", out / "final" / "gt"
        sh(["-m", "splat_train", "render", "--model", str(out / "model.ply"), "--cameras",
            str(cell["align"] / "sparse" / "0"), "--images", str(cell["scene"] / "images"), "--image-list",
            str(cell["test"]), "--out", str(renders), "-q",
            *(["--background", ",".join(str(float(v)) for v in bg)] if bg is not None else [])], logf)
        gt.mkdir(parents=True, exist_ok=True)
        for name in cell["test"].read_text().split():
            link = gt / name
            if not link.exists():
                link.symlink_to((cell["scene"] / "images" / name).resolve())
        sh(["-m", "evaluation", "images", "--pred", str(renders), "--gt", str(gt), "--out", str(metrics),
            "--lpips-nets", "alex", "vgg"], logf)
    m = json.loads(metrics.read_text())
    return {"train": tj, "metrics": m, "values": want, "background": trained}


def record(scene, role: str, n: int, recipe: str, seed: int, iterations: int, result: dict,
           config: dict | None = None) -> dict:
    """The run's record: :data:`RECORD_KEYS` first, then the held-out curve and what ran."""
    tj, m = result["train"], result["metrics"]
    mean = m.get("mean", m)
    c = tj.get("test_curve", {})
    return {
        "scene": scene, "role": role, "n": n, "recipe": recipe, "seed": seed, "iterations": iterations,
        "psnr": mean.get("psnr"), "ssim": mean.get("ssim"), "lpips_alex": mean.get("lpips_alex"),
        "lpips_vgg": mean.get("lpips_vgg"), "gaussians": tj["num_gaussians"], "train_s": tj["wall_time_s"],
        "backend": tj.get("rasterizer"),
        "seed_gaussians": tj.get("seed_gaussians"), "max_gaussians": tj.get("max_gaussians"),
        "best_psnr": c.get("best_test_psnr"), "best_iteration": c.get("best_iteration"),
        "curve": {"iterations": c.get("iterations"), "psnr": c.get("test_psnr"),
                  "coverage": c.get("test_coverage"), "psnr_covered": c.get("test_psnr_covered"),
                  "ssim_covered": c.get("test_ssim_covered"), "lpips_covered": c.get("test_lpips_covered")},
        "config": {"recipe": recipe, **(config or {})}, "schedule": tj.get("schedule"),
        "values": result.get("values"), "device": tj.get("device"), "recorded": time.strftime("%Y-%m-%d"),
    }
