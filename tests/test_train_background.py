"""The config's ``background`` "mean": the training images' mean colour, resolved once by
``splat_train.training.trainer.train`` (RGBA composited on black for it), kept in train.json's config."""

import json

import numpy as np
import pytest

from _train_scene import write_scene
from camio.images import read_image, write_image
from splat_train.config import BACKGROUND_MEAN, TrainConfig
from splat_train.data import load_views, mean_colour
from splat_train.training.trainer import Trainer, inputs_digest, train

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

SHORT = dict(iterations=6, densify_from=2, densify_until=0, opacity_reset_every=1000, sh_increase_every=10,
             eval_every=6, checkpoint_every=6, recipe="paper", device="cpu")


def _pooled_mean(folder, names, background=(0.0, 0.0, 0.0)):
    px = np.concatenate([read_image(folder / n, background).astype(np.float64).reshape(-1, 3) for n in names])
    return px.mean(0)


def test_mean_background_is_the_training_images_pooled_mean_and_is_kept(tmp_path):
    scene = write_scene(tmp_path / "scene", n_views=3, n_test=1)
    names = sorted(p.name for p in scene["images"].iterdir())
    res = train(scene["seed"], scene["cameras"], scene["images"], tmp_path / "run",
                TrainConfig(**SHORT, background=BACKGROUND_MEAN),
                test_cameras=scene["test_cameras"], test_images=scene["test_images"])
    got = json.loads((tmp_path / "run" / "train.json").read_text())["config"]["background"]
    assert got == res.summary["config"]["background"]
    assert np.allclose(got, _pooled_mean(scene["images"], names), atol=5e-7, rtol=0)
    assert 0.0 < min(got) and max(got) < 1.0  # neither black nor white: the scene's own colour
    assert res.summary["test_curve"]["iterations"] == [6]


def test_mean_background_of_rgba_images_is_taken_on_black(tmp_path):
    """Half of each training image transparent: the mean is over the images composited on
    black, so that it does not depend on itself."""
    scene = write_scene(tmp_path / "scene", n_views=3)
    names = sorted(p.name for p in scene["images"].iterdir())
    for n in names:
        rgb = read_image(scene["images"] / n)
        alpha = np.ones(rgb.shape[:2] + (1,), dtype=rgb.dtype)
        alpha[:, : rgb.shape[1] // 2] = 0.0
        write_image(scene["images"] / n, np.concatenate([rgb, alpha], axis=-1))
    train(scene["seed"], scene["cameras"], scene["images"], tmp_path / "run",
          TrainConfig(**SHORT, background=BACKGROUND_MEAN))
    got = json.loads((tmp_path / "run" / "train.json").read_text())["config"]["background"]
    assert np.allclose(got, _pooled_mean(scene["images"], names), atol=5e-7, rtol=0)
    assert not np.allclose(got, _pooled_mean(scene["images"], names, (1.0, 1.0, 1.0)), atol=1e-3)


def test_mean_colour_needs_pixels_and_the_trainer_resolves_it_from_its_views(tmp_path):
    scene = write_scene(tmp_path / "scene", n_views=2)
    with pytest.raises(ValueError, match="pixels"):
        mean_colour(load_views(scene["cameras"], scene["images"], read_pixels=False))
    with pytest.raises(ValueError, match="pixels"):
        mean_colour([])
    views = load_views(scene["cameras"], scene["images"])  # the Trainer takes the mean of the views it is given
    tr = Trainer(TrainConfig(**SHORT, background=BACKGROUND_MEAN), scene["seed"], views, tmp_path / "run")
    assert tr.cfg.background == mean_colour(views) and tr.background_from == BACKGROUND_MEAN
    assert tr.bg.tolist() == pytest.approx(mean_colour(views), abs=1e-7)
    assert inputs_digest(scene["seed"], views, tr.cfg) == \
        inputs_digest(scene["seed"], views, TrainConfig(**SHORT, background=BACKGROUND_MEAN))


@pytest.mark.parametrize("bad", ["grey", [0.5, 0.5], "0,0,0"])
def test_a_background_that_is_neither_a_colour_nor_mean_is_refused(bad):
    with pytest.raises(ValueError, match="background must be 3 numbers"):
        TrainConfig(background=bad)
