"""Held-out coverage along the run (splat_train.training.heldout): the share of a held-out view the model
covers and the PSNR there, in log.parquet and train.json (an older checkpoint's log: tests/test_train_trainer.py)."""

import math

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from _train_scene import write_scene
from splat_train.config import TrainConfig
from splat_train.training.heldout import COVERED_ALPHA, HeldoutScorer, coverage_split
from splat_train.training.runlog import LOG_COLUMNS, TEST_DIAGNOSTICS

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _images(h=6, w=8):
    g = torch.Generator().manual_seed(0)
    target = torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    return target, target.clone()


def test_coverage_split_counts_the_covered_pixels_and_scores_only_them():
    target, rgb = _images()
    alpha = torch.zeros(6, 8, dtype=torch.float64)
    alpha[:, :4] = 1.0
    alpha[0, 4] = COVERED_ALPHA  # the threshold itself counts as covered
    rgb[:, 5:] = 0.0  # an uncovered error the covered PSNR must not see
    rgb[1, 0] += 0.1  # one covered pixel off by 0.1 in every channel
    share, p = coverage_split(rgb.clamp(0, 1), target, alpha)
    covered = 6 * 4 + 1
    assert share == pytest.approx(covered / 48, abs=1e-15)
    err = ((rgb.clamp(0, 1)[1, 0] - target[1, 0]) ** 2).sum().item()  # the only covered error
    assert p == pytest.approx(-10 * math.log10(err / (covered * 3)), abs=1e-9)


def test_coverage_split_of_an_empty_render_is_zero_and_nan_and_of_a_perfect_one_inf():
    target, rgb = _images()
    share, p = coverage_split(torch.zeros_like(rgb), target, torch.zeros(6, 8, dtype=torch.float64))
    assert share == 0.0 and math.isnan(p)
    share, p = coverage_split(rgb, target, torch.ones(6, 8, dtype=torch.float64))
    assert share == 1.0 and p == math.inf


def test_scorer_means_leave_views_without_coverage_out_of_the_covered_psnr():
    target, rgb = _images()
    sc = HeldoutScorer()
    sc("full", rgb, target, torch.ones(6, 8))
    sc("empty", torch.zeros_like(rgb), target, torch.zeros(6, 8))
    half = torch.zeros(6, 8)
    half[:3] = 1.0
    worse = rgb.clone()
    worse[:3] = (worse[:3] + 0.05).clamp(0, 1)
    sc("half", worse, target, half)
    m = sc.means()
    assert m["coverage"] == pytest.approx((1.0 + 0.0 + 0.5) / 3)
    # mean over the two views that cover pixels: inf (exact) and the half view's own
    assert m["psnr_covered"] == math.inf
    sc.reset()
    sc("half", worse, target, half)
    sc("empty", torch.zeros_like(rgb), target, torch.zeros(6, 8))
    assert sc.means()["psnr_covered"] == pytest.approx(coverage_split(worse, target, half)[1])
    sc.reset()
    sc("no alpha", rgb, target)
    assert math.isnan(sc.means()["coverage"]) and math.isnan(sc.means()["psnr_covered"])


@pytest.fixture(scope="module")
def scene(tmp_path_factory, one_thread):
    return write_scene(tmp_path_factory.mktemp("scene"), n_views=4, n_test=2)


def test_the_trainer_logs_the_coverage_of_its_final_model(scene, tmp_path):
    """The last evaluation row's coverage and covered PSNR are those of the final model's
    renders of the test views, recomputed here in float64 from the rasterizer's alpha."""
    from splat_train.data import load_views
    from splat_train.export import render_views
    from splat_train.training.trainer import Trainer

    cfg = TrainConfig(iterations=24, densify_from=5, densify_until=0, opacity_reset_every=1000,
                      sh_increase_every=10, eval_every=12, recipe="paper", device="cpu")
    views = load_views(scene["cameras"], scene["images"])
    tests = load_views(scene["test_cameras"], scene["test_images"])
    tr = Trainer(cfg, scene["seed"], views, tmp_path / "run", tests)
    res = tr.run()
    table = pq.read_table(tmp_path / "run" / "log.parquet")
    assert tuple(table.column_names) == LOG_COLUMNS and set(TEST_DIAGNOSTICS) <= set(LOG_COLUMNS)
    df = table.to_pandas().set_index("iteration")
    ev = df[df["test_psnr"].notna()]
    assert list(ev.index) == [12, 24] and ev["test_coverage"].notna().all()
    assert df["test_coverage"].isna().sum() == len(df) - 2

    renders = {}
    deg = tr.sched.sh_degree_at(tr.iteration, cfg.sh_degree)
    render_views(tr.params, deg, tests, tr.bg,
                 on_render=lambda n, rgb, gt, alpha: renders.update({n: (rgb.double(), gt.double(), alpha.double())}))
    split = [coverage_split(*r) for r in renders.values()]
    assert 0.0 < df.loc[24, "test_coverage"] <= 1.0
    assert df.loc[24, "test_coverage"] == pytest.approx(np.mean([s for s, _ in split]), abs=1e-12)
    assert df.loc[24, "test_psnr_covered"] == pytest.approx(np.mean([p for _, p in split]), abs=1e-4)
    # SSIM over the covered pixels: imgmetrics' definition (the one `evaluation images --alpha-dir`
    # uses) in float64 on the same renders; the trainer scores in float32 (1e-5); LPIPS is off
    from imgmetrics.covered import covered_mask, ssim_covered

    ssims = [ssim_covered(rgb.clamp(0, 1).permute(2, 0, 1), gt.permute(2, 0, 1), covered_mask(alpha))
             for rgb, gt, alpha in renders.values()]
    ssims = [v for v in ssims if not math.isnan(v)]
    assert ssims and df.loc[24, "test_ssim_covered"] == pytest.approx(np.mean(ssims), abs=1e-5)
    assert df["test_lpips_covered"].isna().all()
    c = res.summary["test_curve"]
    assert c["test_coverage"][-1] == c["last_test_coverage"] == pytest.approx(df.loc[24, "test_coverage"])
    assert len(c["test_psnr_covered"]) == len(c["test_ssim_covered"]) == len(c["iterations"]) == 2
    assert "best_test_coverage" not in c  # a diagnostic, not a measure with a best


def test_a_view_too_small_for_lpips_turns_it_off_for_the_run_and_keeps_scoring(caplog):
    """A held-out view under LPIPS-alex's smallest side: LPIPS is NaN from then on, with one
    warning, and PSNR / SSIM / coverage go on (the run does not stop)."""
    from imgmetrics.lpips import LPIPS

    scorer = HeldoutScorer(lpips=False)
    scorer.model = LPIPS("alex")
    rgb, target = torch.rand(20, 24, 3), torch.rand(20, 24, 3)
    with caplog.at_level("WARNING"):
        scorer("small", rgb, target, torch.ones(20, 24))
        scorer("again", rgb, target, torch.ones(20, 24))
    assert scorer.model is None
    assert [r.message for r in caplog.records].count(next(r.message for r in caplog.records)) == 1
    assert "held-out LPIPS off" in caplog.records[0].message and "needs images at least 31 px" in caplog.records[0].message
    m = scorer.means()
    assert math.isnan(m["lpips"]) and np.isfinite(m["psnr"]) and np.isfinite(m["ssim"]) and m["coverage"] == 1.0


def test_covered_ssim_and_lpips_over_every_pixel_are_the_full_image_ones_and_skip_empty_views():
    """A view covered everywhere scores SSIM (and LPIPS-Alex, random weights) over the covered
    pixels as over the image (LPIPS: the map's mean, to 1e-4 of the distance; imgmetrics.lpips);
    a view that covers nothing is left out of the covered means, not counted as 0."""
    from imgmetrics.lpips import LPIPS

    g = torch.Generator().manual_seed(1)
    target = torch.rand(40, 48, 3, generator=g)
    rgb = (target + 0.05 * torch.randn(40, 48, 3, generator=g)).clamp(0, 1)
    sc = HeldoutScorer()
    sc.model = LPIPS("alex")
    sc("full", rgb, target, torch.ones(40, 48))
    full = sc.means()
    assert full["ssim_covered"] == pytest.approx(full["ssim"], abs=1e-6)
    assert full["lpips_covered"] == pytest.approx(full["lpips"], rel=1e-3, abs=1e-6)
    sc("empty", torch.zeros_like(rgb), target, torch.zeros(40, 48))
    both = sc.means()
    assert both["ssim_covered"] == full["ssim_covered"] and both["lpips_covered"] == full["lpips_covered"]
    assert both["ssim"] != full["ssim"]
