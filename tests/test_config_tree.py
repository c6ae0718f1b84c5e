"""The training config as a tree: every flat key names one field of it, the flat dicts written
before (train.json's ``config``) load to the same config, a recipe states only its differences,
a key the user sets wins (a part's key turns the part on, its off value off; a schedule key is
never rescaled), and no config dataclass grows past 25 fields."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from splat_train import tree
from splat_train.config import FLAT_KEYS, TrainConfig, field_of, flat_index, load_config
from splat_train.parts import configs as part_configs
from splat_train.parts.configs import PARTS, DropoutConfig
from splat_train.recipes import DROPGAUSSIAN, PAPER, RECIPE_KEYS, RECIPES, recipe_defaults
from splat_train.strategy import configs as strategy_configs

GOLDEN = Path(__file__).resolve().parent / "data" / "train_golden.json"


def test_every_flat_key_names_exactly_one_field():
    index = flat_index()
    assert list(index)[:len(FLAT_KEYS)] == list(FLAT_KEYS)
    assert len(set(index.values())) == len(index)  # no two keys name one field
    for key in index:
        cls, name = field_of(key)
        assert name in {f.name for f in dataclasses.fields(cls)}, key


def test_no_config_dataclass_has_more_than_25_fields():
    classes = [tree.RunConfig, tree.OptimConfig, tree.RecipeSchedule, tree.ConfigTree, TrainConfig,
               strategy_configs.StrategyConfig, strategy_configs.DefaultStrategyConfig,
               strategy_configs.MCMCStrategyConfig, *PARTS.values()]
    assert {cls.__name__: len(dataclasses.fields(cls)) for cls in classes if len(dataclasses.fields(cls)) > 25} == {}
    assert all(dataclasses.is_dataclass(c) for c in vars(part_configs).values()
               if isinstance(c, type) and issubclass(c, part_configs.PartConfig))


def test_train_json_configs_written_before_load_to_the_same_config():
    """The flat dicts the flat config wrote (tests/data/train_golden.json, train.json's
    ``config``) load and write back unchanged, key order included."""
    for case, rec in json.loads(GOLDEN.read_text()).items():
        flat = rec["config"]
        cfg = TrainConfig.from_flat(flat)
        again = cfg.to_flat()
        assert again == flat, case
        assert list(again) == list(FLAT_KEYS), case
        assert TrainConfig.from_flat(again) == cfg, case


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_a_recipe_round_trips_through_its_flat_keys(name):
    cfg = TrainConfig(recipe=name, iterations=500, device="cpu")
    assert TrainConfig.from_flat(cfg.to_flat()).to_flat() == cfg.to_flat()
    assert cfg.replace(seed=3).to_flat() == {**cfg.to_flat(), "seed": 3}


def test_a_recipe_states_only_its_differences_from_the_base():
    assert PAPER.parts == () and PAPER.run == tree.RunConfig() and PAPER.growth == strategy_configs.StrategyConfig()
    assert DROPGAUSSIAN.parts == (DropoutConfig(rate=0.2),)
    diff = {k for k, v in DROPGAUSSIAN.to_flat().items() if PAPER.to_flat()[k] != v}
    assert diff == {"recipe", "dropout_rate", "densify_grad_threshold", "prune_world_size"}
    # the schedule: paper's is the 3DGS release's over 30,000 iterations, dropgaussian's its
    # release's over 10,000 (the seed code's, RecipeSchedule's defaults)
    assert DROPGAUSSIAN.shares == tree.RecipeSchedule() != PAPER.shares
    assert set(recipe_defaults("paper")) == set(RECIPE_KEYS)


def test_a_set_key_wins_and_a_parts_key_turns_it_on_or_off():
    paper = TrainConfig(recipe="paper", iterations=1000, dropout_rate=0.1)
    assert paper.part("dropout").active() and paper.dropout_rate == 0.1
    assert [c.name for c in paper.parts] == ["dropout"]
    sparse = TrainConfig(recipe="sparse", iterations=1000, dropout_rate=0.0, opacity_decay=1.0)
    assert not sparse.part("dropout").active() and not sparse.part("opacity_decay").active()
    assert sparse.dropout_ramp_fraction == 1.0  # the part's other values stay in the flat dict
    # None keeps the recipe's value; a schedule key set is iterations of this run, never rescaled
    assert TrainConfig(recipe="sparse", iterations=1000, depth_weight=None).depth_weight == 0.05
    s = TrainConfig(recipe="paper", iterations=40, densify_until=30, densify_every=7).schedule()
    assert (s.densify_until, s.densify_every, s.source["densify_every"]) == (30, 7, "set")
    # the user's key wins over the recipe's in every part of the tree
    cfg = load_config({"recipe": "mcmc", "mcmc_growth": "gsplat", "noise_lr": 1.0, "lr_opacity": 0.5,
                       "pose_refine": True, "checkpoint_every": 9}, device="cpu", iterations=100)
    assert (cfg.growth.mcmc.growth, cfg.growth.mcmc.noise_lr, cfg.optim.lr_opacity) == ("gsplat", 1.0, 0.5)
    assert cfg.part("pose").enabled and cfg.run.checkpoint_every == 9


def test_a_bad_value_is_named_by_its_flat_key():
    with pytest.raises(ValueError, match=r"^config: dropout_rate must be"):
        load_config({"dropout_rate": 1.5})
    with pytest.raises(ValueError, match=r"^config: densify_grad_threshold must be"):
        load_config({"densify_grad_threshold": -1})
    with pytest.raises(ValueError, match=r"unknown training config keys \['dropout'\]"):
        load_config({"dropout": 0.1})
