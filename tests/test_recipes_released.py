"""The baselines as released: every value of docs/reference.md section 7's table, resolved from
the recipe (``paper``, ``mcmc``, ``dropgaussian``) at the release's own run length and scaled to
a short run, and every difference from the release named there with its reason.

The table is the one record of the releases' values; this test reads it, so a recipe or a
default that drifts from it fails here until the table (and, for a difference, its reason)
follows.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from splat_train.config import TrainConfig
from splat_train.gaussians import position_lr
from splat_train.parts.dropout import dropout_rate_at
from splat_train.recipes import MIN_DENSIFY_EVERY, RECIPES, SCHEDULE_KEYS
from splat_train.strategy import mcmc

REFERENCE = Path(__file__).resolve().parents[1] / "docs" / "reference.md"
BASELINES = ("paper", "mcmc", "dropgaussian")
SHORT_RUN = 3000  # the sparse-view benchmark's CPU run length


def _section() -> str:
    text = REFERENCE.read_text()
    start = text.index("## 7. Baselines and their sources")
    end = text.find("\n## ", start + 1)
    return text[start:] if end < 0 else text[start:end]


def _value(cell: str) -> float | str:
    cell = cell.strip().strip("`")
    try:
        return float(cell)
    except ValueError:
        return cell.lower()


def _rows() -> list[tuple[str, str, float | str, float | str, str]]:
    """(recipe, key, release, project, source) for every row of the table."""
    rows = []
    for line in _section().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[0] in BASELINES:
            rows.append((cells[0], cells[1], _value(cells[2]), _value(cells[3]), cells[4]))
    return rows


def _named_differences() -> set[tuple[str, str]]:
    """(recipe, key) pairs named in the section's list of differences."""
    text = _section()
    listed = text[text.index("Named differences"):]
    out = set()
    for bullet in re.split(r"\n- ", listed)[1:]:
        head = bullet.split(":", 1)[0]
        out |= set(re.findall(r"`(\w+)`\s+`(\w+)`", head))
    return out


def _same(a: float | str, b: float | str) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=0.0)
    return a == b


def resolved(recipe: str, key: str, iterations: int) -> float | str:
    """What the project runs for ``key`` under ``recipe`` at ``iterations``, in the table's units."""
    cfg = TrainConfig(recipe=recipe, iterations=iterations, device="cpu")
    if key in SCHEDULE_KEYS:
        return float(getattr(cfg.schedule(), key))
    if key == "iterations":
        return float(cfg.iterations)
    if key == "position_lr_steps":  # the iteration at which the position rate reaches its final value
        final = position_lr(cfg, cfg.iterations, extent=1.0)
        assert math.isclose(final, cfg.lr_position_final, rel_tol=1e-9)
        return float(cfg.iterations)
    if key == "l1_weight":
        return 1.0 - cfg.lambda_dssim
    if key == "background":
        return "black" if cfg.background == [0.0, 0.0, 0.0] else str(cfg.background)
    if key in ("init_opacity", "init_scale"):
        return "seed"  # every recipe keeps the seed PLY's own (splat_train.gaussians.params_from_cloud)
    if key == "growth":
        return mcmc.GROWTH
    if key == "noise_gate_k":
        return mcmc.NOISE_K
    if key == "noise_gate_t":
        return mcmc.NOISE_T
    if key == "relocation_min_opacity":
        return float(_mcmc_strategy(cfg, cap=10).min_opacity)
    if key == "cap_over_seed":  # the cap a seed far over the per-pixel cap gets, over its size
        seed = 1_000_000
        return cfg.max_gaussians_for(train_pixels=1000, seed_size=seed) / seed
    if key == "dropout_ramp_fraction":  # where the rate first reaches its final value, as a share of the run
        first = next(it for it in range(1, iterations + 1)
                     if dropout_rate_at(it, iterations, cfg.dropout_rate, cfg.dropout_ramp_fraction) >= cfg.dropout_rate)
        return first / iterations
    value = getattr(cfg, key)
    return value if isinstance(value, str) else float(value)


def _mcmc_strategy(cfg: TrainConfig, cap: int, seed_size: int = 0):
    """The mcmc strategy a run of ``cfg`` builds, with the cap ``cap``."""
    return cfg.growth.build("mcmc", cfg.schedule(), cap, seed_size)


ROWS = _rows()


def _release_iterations(recipe: str) -> int:
    return int(next(r[2] for r in ROWS if r[0] == recipe and r[1] == "iterations"))


def test_the_table_covers_every_baseline_and_its_schedule():
    assert len(ROWS) > 50
    for recipe in BASELINES:
        keys = [r[1] for r in ROWS if r[0] == recipe]
        assert len(keys) == len(set(keys)), recipe
        assert "iterations" in keys
        assert set(SCHEDULE_KEYS) <= set(keys), recipe
        assert all(r[4] for r in ROWS if r[0] == recipe), "every row names its source"


@pytest.mark.parametrize("row", ROWS, ids=[f"{r[0]}-{r[1]}" for r in ROWS])
def test_the_recipe_resolves_to_the_table_at_the_release_length(row):
    recipe, key, _, project, _ = row
    assert _same(resolved(recipe, key, _release_iterations(recipe)), project), (recipe, key)


def test_every_difference_from_a_release_is_named():
    differ = {(r[0], r[1]) for r in ROWS if not _same(r[2], r[3])}
    named = _named_differences()
    assert differ == named, (f"differences without a reason: {sorted(differ - named)}; "
                             f"named but not different: {sorted(named - differ)}")


def _scaled(recipe: str, key: str, count: float, release_iterations: int, n: int) -> int:
    """A release's schedule count on a run of ``n`` iterations: its fraction of the release's
    run (gsplat's ``steps_scaler``); the period of ``paper`` and ``dropgaussian`` absolute, as
    their code keeps it; a scaled period at least MIN_DENSIFY_EVERY."""
    if count == 0:
        return 0
    if key == "densify_every":
        if RECIPES[recipe].shares.densify_every_count is not None:
            return int(count)
        return max(MIN_DENSIFY_EVERY, round(count / release_iterations * n))
    return max(1, round(count / release_iterations * n))


@pytest.mark.parametrize("recipe", BASELINES)
def test_the_schedule_scales_to_a_short_run_as_the_releases_fractions(recipe):
    n_release = _release_iterations(recipe)
    got = TrainConfig(recipe=recipe, iterations=SHORT_RUN, device="cpu").schedule()
    every = _scaled(recipe, "densify_every", next(r[3] for r in ROWS if r[0] == recipe and r[1] == "densify_every"),
                    n_release, SHORT_RUN)
    for r_recipe, key, _, project, _ in ROWS:
        if r_recipe != recipe or key not in SCHEDULE_KEYS:
            continue
        want = _scaled(recipe, key, project, n_release, SHORT_RUN)
        if key == "opacity_reset_every" and want:
            want = max(want, 3 * every)  # a reset never comes sooner than 3 densifications
        assert getattr(got, key) == want, (recipe, key, getattr(got, key), want)


def test_paper_at_a_short_run_is_the_release_in_proportion():
    """The numbers the table implies at 3,000 iterations, written out."""
    s = TrainConfig(recipe="paper", iterations=SHORT_RUN, device="cpu").schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every, s.sh_increase_every) == \
        (50, 1500, 100, 300, 100)
    s = TrainConfig(recipe="mcmc", iterations=SHORT_RUN, device="cpu").schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every, s.sh_increase_every) == \
        (50, 2500, 20, 0, 100)
    s = TrainConfig(recipe="dropgaussian", iterations=SHORT_RUN, device="cpu").schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every, s.sh_increase_every) == \
        (150, 3000, 100, 900, 300)


def test_mcmc_grows_from_a_seed_that_fills_its_per_pixel_cap():
    """3DGS's random initialisation (0.25 per training pixel) is over mcmc's 0.175: the cap rises
    above the seed, so the run grows from it as the release's runs grow from their random points."""
    pixels = 3 * 200 * 200
    cfg = TrainConfig(recipe="mcmc", iterations=SHORT_RUN, device="cpu")
    per_pixel = cfg.max_gaussians_for(pixels, 0)
    assert per_pixel == int(0.175 * pixels)
    random_seed = int(0.25 * pixels)
    cap = cfg.max_gaussians_for(pixels, random_seed)
    assert cap == math.ceil(1.5 * random_seed) > random_seed
    strategy = _mcmc_strategy(cfg, cap, random_seed)
    steps = mcmc.refine_steps(strategy.refine_from, strategy.refine_until, strategy.refine_every, strategy.refine_until)
    assert mcmc.growth_target(random_seed, 1, steps, random_seed, cap) == int(1.05 * random_seed)
    # a few measured points stay under the per-pixel cap, which holds for them
    assert cfg.max_gaussians_for(pixels, 95) == per_pixel
