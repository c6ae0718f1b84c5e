"""A run's training configuration: a recipe's config tree with the user's flat keys over it.

:class:`TrainConfig` (a :class:`splat_train.tree.ConfigTree`) holds the run (:class:`RunConfig`: iterations, seed, device, threads,
checkpoints, evaluation), the optimisation (:class:`OptimConfig`: learning rates, SH degree,
loss, background), the growth strategy (``growth``, :class:`splat_train.strategy.configs.StrategyConfig`), the
training parts (a tuple of :mod:`splat_train.parts.configs` configs) and the recipe's schedule
as shares of the run (:class:`RecipeSchedule`). A recipe (:mod:`splat_train.recipes`) is such a
tree, stating only its differences from the base.

What a user writes stays one flat dict (``--config`` JSON, the ``python -m splat_train``
flags, the workflow's ``train:`` keys, ``train.json``'s ``config``): every flat key names exactly
one field of the tree (:func:`flat_index`; :meth:`TrainConfig.from_flat`,
:meth:`TrainConfig.to_flat`). ``TrainConfig(**flat)`` starts from the recipe ``recipe`` names
and sets the keys given over it: a key the user sets wins; None for a key a recipe decides
(:data:`RECIPE_KEYS`) keeps the recipe's value; a part's key turns the part's config on in the
tree, its off value turns the part off.

Schedule keys (densify_from, densify_until, densify_every, opacity_reset_every,
sh_increase_every) are iterations of this run: the recipes give them as shares of the run,
resolved once per run by :meth:`TrainConfig.schedule` and printed by the trainer; a number the
user writes is never rescaled.

At the paper's 10,000 iterations the ``paper`` recipe gives the seed code's counts: densify
from 500 to 10000 every 100, reset opacity every 3000, raise the SH degree every 1000 up to 3.
A shorter run compresses them in proportion (the densification *period* stays 100 in
``paper``: densifying 5x as often in a 5x shorter run grew 4000 seeds to 120k Gaussians by
iteration 400 on the 256 px synthetic scene); the scaled opacity-reset period is kept >= 3
densification periods (a reset needs time to recover). The learning rates are not scaled; the
position rate decays exponentially over the whole run whatever its length.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from splat_train.parts.configs import PartConfig
from splat_train.recipes import DEFAULT_RECIPE, recipe_config
from splat_train.strategy.configs import StrategyConfig
from splat_train.tree import (BACKGROUND_BLACK, BACKGROUND_MEAN, FLAT_KEYS, MIN_DENSIFY_EVERY, RECIPE_KEYS,  # noqa: F401
                              SCHEDULE_KEYS, SEED, ConfigTree, OptimConfig, RecipeSchedule, RunConfig, Schedule,
                              apply_flat, check_keys, field_of, flat_index)

__all__ = ["TrainConfig", "ConfigTree", "RunConfig", "OptimConfig", "RecipeSchedule", "Schedule", "DEFAULT_ITERATIONS",
           "PAPER_ITERATIONS", "default_iterations", "resolve_device", "RESUME_FREE_KEYS", "POSE_KEYS",
           "BACKGROUND_MEAN", "BACKGROUND_BLACK", "SCHEDULE_KEYS", "RECIPE_KEYS", "FLAT_KEYS",
           "MIN_DENSIFY_EVERY", "flat_index", "field_of", "load_config", "SEED"]

# Training iterations on a CPU when none are given: finishes in minutes on a 2-core machine;
# on a GPU the paper's 10,000 (PAPER_ITERATIONS). Timings: benchmarks/README.md.
DEFAULT_ITERATIONS = 1000
# The paper's budget ("10K iterations", docs/reference.md section 3): the default on a GPU, and the
# run length the seed code's schedule was written for.
PAPER_ITERATIONS = 10000
# Config fields that do not change the optimisation result: they may differ on resume.
# The rasterizer backend is among them: the backends are parity-tested against one reference
# (tests/test_raster_parity.py, tests/test_raster_gsplat.py), so a run started on CPU may go on
# on a GPU, and checkpoints written before the key existed still resume.
RESUME_FREE_KEYS = ("checkpoint_every", "keep_checkpoints", "eval_every", "num_threads", "kernel_threads",
                    "rasterizer", "eval_lpips", "lpips_weights")
# Config fields that only matter with pose_refine: a run without refinement may resume a
# checkpoint that differs in them (or predates them).
POSE_KEYS = ("lr_pose", "pose_refine_from", "pose_warmup", "pose_refine_focal", "lr_focal")


def resolve_device(device: str) -> str:
    """The config's ``device`` with 'auto' resolved: 'cuda' when torch sees a CUDA GPU, else 'cpu'."""
    if device == "auto":
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def default_iterations(device: str) -> int:
    """Iterations of a run that names none: :data:`PAPER_ITERATIONS` where training runs on a
    GPU (``device`` 'cuda', or 'auto' with a CUDA device visible), :data:`DEFAULT_ITERATIONS`
    on a CPU."""
    return PAPER_ITERATIONS if resolve_device(device).startswith("cuda") else DEFAULT_ITERATIONS


@dataclass(frozen=True, init=False)
class TrainConfig(ConfigTree):
    """A run's training config: a :class:`splat_train.tree.ConfigTree` made from a recipe and
    flat keys.

    ``TrainConfig(recipe="sparse", iterations=1000, dropout_rate=0.1)`` (or :meth:`from_flat`)
    is the recipe's tree with the keys set over it (module docstring), ``iterations`` resolved
    (:func:`default_iterations`) and the rasterizer checked; ``TrainConfig()`` is the default
    recipe's. Given tree fields (``run=``, ``optim=``, ``growth=``, ``parts=``, ``shares=``) and
    no flat key, it is that tree as it is (what :func:`dataclasses.replace` makes).
    """

    def __init__(self, recipe: str | None = None, run: RunConfig | None = None, optim: OptimConfig | None = None,
                 growth: StrategyConfig | None = None, parts: tuple[PartConfig, ...] | None = None,
                 shares: RecipeSchedule | None = None, **flat: Any) -> None:
        given = dict(run=run, optim=optim, growth=growth, parts=parts, shares=shares)
        resolve = bool(flat) or all(v is None for v in given.values())
        if resolve:  # the recipe's tree under the flat keys
            base = recipe_config(DEFAULT_RECIPE if recipe is None else recipe)
            recipe = base.recipe
        else:  # a tree as it is
            base = ConfigTree(recipe=recipe)  # the configs' defaults; checks the name
        tree = {k: (v if v is not None else getattr(base, k)) for k, v in given.items()}
        ConfigTree.__init__(self, recipe, **apply_flat(tree, flat))
        if resolve:
            if self.run.iterations is None:
                object.__setattr__(self, "run", dataclasses.replace(
                    self.run, iterations=default_iterations(self.run.device)))
            from splat_train.render.rasterize import BACKENDS

            if self.run.rasterizer not in BACKENDS:
                raise ValueError(f"rasterizer must be one of {BACKENDS}, got {self.run.rasterizer!r}")

    @classmethod
    def from_flat(cls, data: dict[str, Any]) -> "TrainConfig":
        """The config of a flat dict (``--config`` JSON, train.json's ``config``); unknown keys
        raise ValueError naming them."""
        check_keys(data)
        return cls(**data)

    def replace(self, **overrides: Any) -> "TrainConfig":
        """A copy with the flat keys ``overrides`` set; unknown keys raise ValueError naming them."""
        check_keys(overrides)
        return TrainConfig(**{**self.to_flat(), **overrides})


def load_config(overrides: str | Path | dict | None = None, **cli: Any) -> TrainConfig:
    """Defaults, then JSON overrides (a file path, a JSON string or a dict), then ``cli``
    values that are not None (the CLI flags win).

    Raises:
        ValueError: one line naming the source ("--config FILE: lr_opacity must be a finite
            number >= 0, got -1"): an unreadable or malformed file, an unknown key, a value of
            the wrong type or out of its field's range.
    """
    data: dict[str, Any] = {}
    source = "config"
    if isinstance(overrides, dict):
        data = dict(overrides)
    elif overrides is not None:
        text = str(overrides)
        p = Path(text)
        source = f"--config {text}" if p.is_file() else "--config (JSON string)"
        try:
            data = json.loads(p.read_text() if p.is_file() else text)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{source}: must be a JSON file or a JSON object string: {exc}") from exc
        if not isinstance(data, dict):
            raise ValueError(f"{source}: must hold a JSON object, got {type(data).__name__}")
    data.update({k: v for k, v in cli.items() if v is not None})
    try:
        return TrainConfig.from_flat(data)  # made once, so an unset iterations follows the device given
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{source}: {exc}") from None
