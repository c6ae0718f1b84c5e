"""docs/reference.md section 3a states the `sparse` recipe's values as the code has them.

The values live in one place, the ``SPARSE`` preset of splat_train/recipes.py (and the
defaults of the configs it does not change); the reference page restates them for a reader. Each
check below builds the page's phrase from the code's value, so a value changed in the code
without the page (or the page without the code) fails here, naming the phrase to update.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from splat_train.parts.binocular import SMOOTH_WEIGHT
from splat_train.parts.configs import BinocularConfig, DepthPriorConfig
from splat_train.recipes import BACKGROUND_MEAN, RECIPES

ROOT = Path(__file__).resolve().parents[1]
SPARSE = RECIPES["sparse"].to_flat()  # the flat keys of the recipe
SHARES = RECIPES["sparse"].shares  # its schedule as shares of the run
DEFAULTS = {"depth_min_samples": DepthPriorConfig().min_samples, "binocular_shift": BinocularConfig().shift}


def _section_3a() -> str:
    text = (ROOT / "docs" / "reference.md").read_text()
    start = text.index("## 3a.")
    return " ".join(text[start:text.index("\n## ", start + 1)].split())  # one line: phrases may wrap


def _pct(fraction: float) -> str:
    return f"{fraction * 100:g} %"


PHRASES = [
    f"p ramping linearly from 0 to {SPARSE['dropout_rate']:g} over the run",
    f"weight {SPARSE['depth_weight']:g} (FSGS's) ramped in over the first {_pct(SPARSE['depth_ramp_fraction'])} of the run",
    f"fewer than {DEFAULTS['depth_min_samples']} prior samples",
    f"shifted sideways by up to {_pct(DEFAULTS['binocular_shift'])} of its median rendered depth",
    f"(weight {SPARSE['binocular_weight']:g}) plus {SMOOTH_WEIGHT:g} x an edge-aware disparity smoothness",
    f"the room under {SPARSE['gaussians_per_pixel']:g} Gaussians per training pixel",
    f"densify every {SHARES.densify_every_count} iterations from {_pct(SHARES.densify_from)} of the run to its end",
    f"every opacity x {SPARSE['opacity_decay']:g} after each iteration from the densification start",
    f"{SPARSE['opacity_reg']:g} x the mean opacity added to the loss",
    f"shrinks towards the cap (`{SPARSE['seed_over_cap']}`)",
]


@pytest.mark.parametrize("phrase", PHRASES)
def test_reference_states_the_sparse_value_the_code_has(phrase):
    assert phrase in _section_3a(), f"docs/reference.md section 3a should say: {phrase!r} (splat_train/recipes.py)"


def test_reference_states_the_schedule_and_background_the_code_has():
    # growth to the end of the run, no opacity reset, binocular term from the densification start
    assert SHARES.densify_until == 1.0 and SHARES.opacity_reset_every is None
    assert SPARSE["binocular_from_fraction"] == SHARES.densify_from
    assert SPARSE["dropout_ramp_fraction"] == 1.0
    section = _section_3a()
    assert "never resetting opacity" in section and "from the densification start on" in section
    # the colour behind the model: the training images' mean in `sparse`, black in the field's recipes
    assert SPARSE["background"] == BACKGROUND_MEAN
    assert all(RECIPES[name].optim.background == [0.0, 0.0, 0.0] for name in ("paper", "dropgaussian", "mcmc"))
    assert "`sparse` trains against the mean colour of the training images" in section
    assert "the field's recipes against black" in section
