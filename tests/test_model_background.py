"""The colour behind a model, from the recipe to every later render: each recipe gives a
``background`` (a config value wins), train.json keeps the colour and what was asked
(``background_from``), and ``render`` / ``testpose`` draw a model against the colour it was trained
against unless told otherwise, so that the renders a user makes match the trainer's own."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from camio.images import read_image
from splat_train.__main__ import main
from splat_train.config import TrainConfig
from splat_train.export import model_background
from splat_train.recipes import BACKGROUND_BLACK, BACKGROUND_MEAN, RECIPES, VALUE_KEYS
from tests._train_scene import write_scene

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_every_recipe_gives_a_background_and_a_set_one_wins(monkeypatch):
    assert "background" in VALUE_KEYS
    for name, preset in RECIPES.items():  # the field's recipes keep 3DGS's black; sparse asks for the mean
        want = BACKGROUND_MEAN if name == "sparse" else BACKGROUND_BLACK
        assert preset.optim.background == (want if want == BACKGROUND_MEAN else list(want)), name
        assert TrainConfig(recipe=name).background == (want if want == BACKGROUND_MEAN else list(want))
    assert TrainConfig().background == BACKGROUND_MEAN  # the default recipe
    for name in RECIPES:  # a set colour wins over the recipe's
        assert TrainConfig(recipe=name, background=[1, 1, 1]).background == [1.0, 1.0, 1.0]
        assert TrainConfig(recipe=name, background="mean").background == BACKGROUND_MEAN
    paper = RECIPES["paper"]
    monkeypatch.setitem(RECIPES, "paper", replace(paper, optim=replace(paper.optim, background=BACKGROUND_MEAN)))
    assert TrainConfig(recipe="paper").background == BACKGROUND_MEAN


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A short `paper` run against the training images' mean colour, with two held-out views."""
    root = tmp_path_factory.mktemp("bg")
    paths = write_scene(root / "scene", n_views=3, width=40, height=30, n_test=2)
    out = root / "run"
    cfg = {"recipe": "paper", "background": "mean", "densify_until": 0}
    assert main(["--seed-ply", str(paths["seed"]), "--cameras", str(paths["cameras"]), "--images", str(paths["images"]),
                 "--test-cameras", str(paths["test_cameras"]), "--test-images", str(paths["test_images"]),
                 "--out", str(out), "--iterations", "30", "--rasterizer", "cpu", "--eval-every", "30",
                 "--checkpoint-every", "30", "--config", json.dumps(cfg), "-q"]) == 0
    return paths, out


def _render(paths, model, out, *extra):
    assert main(["render", "--model", str(model), "--cameras", str(paths["test_cameras"]),
                 "--images", str(paths["test_images"]), "--out", str(out), "-q", *extra]) == 0
    return {p.name: read_image(p).astype(np.float64) for p in sorted(out.glob("*.png"))}


def test_train_json_keeps_the_colour_and_that_it_was_the_mean(trained):
    paths, out = trained
    tj = json.loads((out / "train.json").read_text())
    assert tj["background_from"] == "mean"
    rgb, source = model_background(out / "model.ply")
    assert list(rgb) == tj["config"]["background"] and source == str(out / "train.json")
    assert 0.0 < min(rgb) and max(rgb) < 1.0


def test_render_and_testpose_draw_the_model_against_its_training_colour(trained, tmp_path):
    paths, out = trained
    rgb = model_background(out / "model.ply")[0]
    default = _render(paths, out / "model.ply", tmp_path / "default")
    told = _render(paths, out / "model.ply", tmp_path / "told", "--background", ",".join(map(str, rgb)))
    black = _render(paths, out / "model.ply", tmp_path / "black", "--background", "0,0,0")
    assert default.keys() == told.keys() == black.keys() and len(default) == 2
    for name in default:
        assert np.array_equal(default[name], told[name]), name
        # the trainer's own held-out render of the final model (renders/) is the same image
        assert np.abs(default[name] - read_image(out / "renders" / name).astype(np.float64)).max() <= 1 / 255, name
        assert np.abs(default[name] - black[name]).max() > 0.05, name  # the colour shows where the model is thin
    # test-pose with no steps renders the start, against the same colour
    assert main(["testpose", "--model", str(out / "model.ply"), "--cameras", str(paths["test_cameras"]),
                 "--images", str(paths["test_images"]), "--out", str(tmp_path / "tp"), "--steps", "0",
                 "--rasterizer", "cpu", "-q"]) == 0
    for name in default:
        tp = read_image(tmp_path / "tp" / "renders" / name).astype(np.float64)
        assert np.abs(tp - default[name]).max() <= 1 / 255, name


def test_a_model_without_its_train_json_is_drawn_on_black(trained, tmp_path):
    paths, out = trained
    alone = tmp_path / "alone" / "model.ply"
    alone.parent.mkdir()
    shutil.copy(out / "model.ply", alone)
    assert model_background(alone) == (BACKGROUND_BLACK, "default")
    (alone.parent / "train.json").write_text("{not json")  # a damaged one is refused, not taken for black
    with pytest.raises(ValueError, match="train.json: not JSON"):
        model_background(alone)
    (alone.parent / "train.json").unlink()
    default = _render(paths, alone, tmp_path / "r")
    black = _render(paths, out / "model.ply", tmp_path / "b", "--background", "0,0,0")
    for name in default:
        assert np.array_equal(default[name], black[name]), name


@pytest.mark.parametrize("bad", ["1,1", "0,0,0,0", "white", "0,0,1.5", "nan,0,0"])
def test_render_refuses_a_background_it_cannot_draw(trained, tmp_path, capsys, bad):
    """A malformed or out-of-range ``--background`` is one error line and exit 2, nothing written."""
    paths, out = trained
    dest = tmp_path / "r"
    assert main(["render", "--model", str(out / "model.ply"), "--cameras", str(paths["test_cameras"]),
                 "--images", str(paths["test_images"]), "--out", str(dest), "--background", bad]) == 2
    err = capsys.readouterr().err
    assert "--background must be three numbers in [0, 1]" in err and repr(bad) in err, err
    assert not dest.exists()
