"""Adding a recipe and a training part through the public registration API (docs/contracts.md,
"Adding a recipe", "Adding a training part").

A module outside the project registers a recipe (``paper`` at half the opacity rate: a preset of
one changed value, :func:`splat_train.recipes.register_recipe`) and a part (a counter of the
Gaussians' steps, :func:`splat_train.parts.configs.register_part`), then runs the project's own
``python -m splat_train`` entry point. The help lists both, ``--recipe`` and ``--config`` take
them, and the trainer runs the part through its interface: its summary lands in train.json, its
key in train.json's ``config``, beside the recipe's changed value.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from _train_scene import write_scene

ROOT = Path(__file__).resolve().parents[1]

PLUGIN = '''
from dataclasses import dataclass, replace
from typing import Annotated, ClassVar

from splat_train import recipes
from splat_train.fields import ITERATION
from splat_train.parts.configs import PartConfig, register_part
from splat_train.parts.base import TrainPart


class StepCounter(TrainPart):
    """Counts the steps of the Gaussians it follows."""

    name = "counter"

    def __init__(self, every: int) -> None:
        self.every, self.steps = every, 0

    def after_step(self, iteration, params):
        self.steps += iteration % self.every == 0

    def summary(self):
        return {"counter_steps": self.steps}


@register_part
@dataclass(frozen=True)
class CounterConfig(PartConfig):
    """A step counter (a test part).

    Attributes:
        every: count every this many iterations (0 = off).
    """

    name: ClassVar[str] = "counter"
    flat_prefix: ClassVar[str] = "counter_"

    every: Annotated[int, ITERATION] = 0

    def active(self):
        return self.every > 0

    def build(self, ctx):
        return StepCounter(self.every)


recipes.register_recipe(replace(recipes.PAPER, recipe="paper_slow",
                                optim=replace(recipes.PAPER.optim, lr_opacity=recipes.PAPER.optim.lr_opacity / 2)),
                        "paper at half the opacity rate")
'''
MAIN = "import sys, counter_plugin; from splat_train.__main__ import _cli; sys.exit(_cli())"


def _run(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    (tmp_path / "counter_plugin.py").write_text(PLUGIN)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(tmp_path)])}
    return subprocess.run([sys.executable, "-c", MAIN, *args], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=300)


def test_the_help_lists_the_added_recipe_and_part(tmp_path):
    proc = _run(tmp_path, "-h")
    assert proc.returncode == 0, proc.stderr
    text = " ".join(proc.stdout.split())
    assert "'paper_slow': paper at half the opacity rate" in text
    assert "counter (counter_every)" in text


@pytest.mark.usefixtures("one_thread")
def test_the_config_and_the_trainer_take_the_added_recipe_and_part(tmp_path):
    scene = write_scene(tmp_path / "scene", n_views=3)
    out = tmp_path / "run"
    proc = _run(tmp_path, "--seed-ply", str(scene["seed"]), "--cameras", str(scene["cameras"]), "--images",
                str(scene["images"]), "--out", str(out), "--iterations", "6", "--device", "cpu",
                "--recipe", "paper_slow", "--config", json.dumps({"counter_every": 2}), "-q")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "train.json").read_text())
    assert summary["counter_steps"] == 3  # iterations 2, 4, 6
    cfg = summary["config"]
    assert (cfg["recipe"], cfg["counter_every"], cfg["lr_opacity"]) == ("paper_slow", 2, 0.025)
    # a bad value of the part's key is refused naming it, before anything is written
    bad = _run(tmp_path, "--seed-ply", str(scene["seed"]), "--cameras", str(scene["cameras"]), "--images",
               str(scene["images"]), "--out", str(tmp_path / "bad"), "--config", '{"counter_every": -1}')
    assert bad.returncode == 2 and "counter_every must be" in bad.stderr and "Traceback" not in bad.stderr
    assert not (tmp_path / "bad").exists()


def test_an_added_part_left_off_changes_no_run(tmp_path):
    """A run without the new part keeps its inputs digest (so its checkpoints resume): the
    part's keys at their off value are no part of the digest."""
    scene = write_scene(tmp_path / "scene", n_views=3)
    code = ("import sys; sys.argv[1:] and __import__(sys.argv[1]); "
            "from splat_train.config import TrainConfig; from splat_train.data import load_views; "
            "from splat_train.training.trainer import inputs_digest; "
            f"views = load_views({str(scene['cameras'])!r}, {str(scene['images'])!r}); "
            f"print(inputs_digest({str(scene['seed'])!r}, views, TrainConfig(recipe='paper', iterations=9)))")
    (tmp_path / "counter_plugin.py").write_text(PLUGIN)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(tmp_path)])}
    digests = [subprocess.run([sys.executable, "-c", code, *plugin], capture_output=True, text=True, cwd=ROOT,
                              env=env, timeout=300) for plugin in ([], ["counter_plugin"])]
    assert all(p.returncode == 0 for p in digests), [p.stderr[-2000:] for p in digests]
    assert digests[0].stdout == digests[1].stdout and len(digests[0].stdout.strip()) == 64
