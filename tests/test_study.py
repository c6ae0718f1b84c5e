"""The initialisation study: grid expansion, the oracle's confidence modes, the floater
measure on a constructed case, and the aggregation's interval against a float64 reference."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy.stats import spearmanr

from evaluation.metrics.floaters import floater_fraction, trajectory_radius
from evaluation.initialisers.oracle import OracleNoise, make_oracle_predictions, reassign_confidence
from evaluation.study.stats import paired_differences, summarise, t_interval
from evaluation.study.grid import ZERO, expand_cells

from test_oracle import NAMES, scene  # noqa: F401  (the oracle's scene fixture)


# ----------------------------------------------------------------------------- grid


def test_expand_cells_one_axis_at_a_time():
    cells = expand_cells({
        "seeds": [0],
        "points": {"vggt_like_sim": {"rot_deg": 1.0, "depth_rel": 0.02}},
        "axes": [{"param": "rot_deg", "levels": [0, 2.0]},  # level 0 equals zero: dropped
                 {"param": "conf_mode", "levels": ["noise", "anti"], "base": "vggt_like_sim"}],
    })
    assert list(cells) == ["zero", "vggt_like_sim", "rot_deg-2", "conf_mode-noise", "conf_mode-anti"]
    assert cells["zero"]["noise"] == {**ZERO}
    assert cells["rot_deg-2"]["noise"] == {**ZERO, "rot_deg": 2.0}
    anti = cells["conf_mode-anti"]["noise"]
    assert anti == {**cells["vggt_like_sim"]["noise"], "conf_mode": "anti"}
    assert cells["conf_mode-anti"]["base"] == "vggt_like_sim"


@pytest.mark.parametrize("study, message", [
    ({"axes": [{"param": "focal", "levels": [1]}]}, "focal"),
    ({"axes": [{"param": "rot_deg", "levels": [1], "base": "nope"}]}, "nope"),
    ({"axes": [{"param": "conf_mode", "levels": ["sometimes"]}]}, "sometimes"),
    ({"points": {"p": {"rot": 1}}}, "rot"),
])
def test_expand_cells_errors_name_the_bad_value(study, message):
    with pytest.raises(ValueError, match=message):
        expand_cells(study)


# ----------------------------------------------------------------------------- conf_mode


def _conf_vs_error(scene_dir, mode: str) -> float:
    """Spearman correlation of confidence and |injected relative depth error| (foreground)."""
    noise = OracleNoise(depth_rel=0.05, outlier_frac=0.1, conf_mode=mode)
    arrays, _ = make_oracle_predictions(scene_dir, NAMES, noise, seed=3)
    exact, _ = make_oracle_predictions(scene_dir, NAMES, OracleNoise(), seed=3)
    fg = exact["depth"] > 0
    err = np.abs(arrays["depth"][fg] / exact["depth"][fg] - 1)
    return float(spearmanr(arrays["world_points_conf"][fg], err).statistic)


def test_conf_mode_ranked_noise_anti(scene):  # noqa: F811
    ranked, noise, anti = (_conf_vs_error(scene, m) for m in ("ranked", "noise", "anti"))
    assert ranked < -0.99  # conf_noise 0: confidence is a decreasing function of |e|
    assert anti > 0.99
    assert abs(noise) < 0.1


def test_conf_mode_keeps_values_and_the_rest_of_the_draws(scene):  # noqa: F811
    out = {m: make_oracle_predictions(scene, NAMES, OracleNoise(depth_rel=0.05, rot_deg=1.0, conf_mode=m),
                                      seed=1)[0] for m in ("ranked", "noise", "anti")}
    for m in ("noise", "anti"):
        np.testing.assert_array_equal(out[m]["world_points"], out["ranked"]["world_points"])
        np.testing.assert_array_equal(out[m]["cam_from_world"], out["ranked"]["cam_from_world"])
        for s in range(len(NAMES)):  # the same confidence values per view, re-assigned
            np.testing.assert_array_equal(np.sort(out[m]["world_points_conf"][s].ravel()),
                                          np.sort(out["ranked"]["world_points_conf"][s].ravel()))


def test_reassign_confidence_anti_reverses_ranks_and_keeps_background():
    conf = np.array([[5.0, 1.0], [3.0, 4.0]])
    valid = np.array([[True, False], [True, True]])
    out = reassign_confidence(conf, valid, "anti", np.random.default_rng(0))
    np.testing.assert_array_equal(out, [[3.0, 1.0], [5.0, 4.0]])
    with pytest.raises(ValueError, match="conf_mode"):
        reassign_confidence(conf, valid, "bogus", np.random.default_rng(0))
    with pytest.raises(ValueError, match="conf_mode"):
        OracleNoise(conf_mode="bogus")


# ----------------------------------------------------------------------------- floaters


def test_floater_fraction_constructed_case():
    # four Gaussians at known distances from the surface; tau = 0.1
    dist = np.array([0.0, 0.05, 0.2, 3.0])
    alpha = np.array([0.5, 0.1, 0.3, 0.1])
    r = floater_fraction(dist, alpha, tau=0.1)
    assert r["floater_frac"] == pytest.approx(0.4 / 1.0)
    assert r["opacity_mass"] == pytest.approx(1.0)
    assert r["n_gaussians"] == 4
    # opacity-weighted mean of min(d, 10 tau) / tau = (0 + 0.05 + 0.6 + 1.0) / 0.1 / 1.0
    assert r["mean_dist_over_tau"] == pytest.approx((0.1 * 0.05 + 0.3 * 0.2 + 0.1 * 1.0) / 0.1)
    assert math.isnan(floater_fraction(np.zeros(0), np.zeros(0), 0.1)["floater_frac"])
    with pytest.raises(ValueError, match="tau"):
        floater_fraction(dist, alpha, tau=0.0)


def test_surface_distance_on_the_synthetic_mesh(tmp_path):
    """A point on the ground (z = 0, away from the objects) is on the surface; one lifted by
    h above it (and below everything else) is h away."""
    import json

    from evaluation.metrics.floaters import surface_distance

    (tmp_path / "synthetic.json").write_text(json.dumps({"seed": 0}))
    d = surface_distance(tmp_path, np.array([[-6.0, -8.0, 0.0], [-6.0, -8.0, 0.25]]))
    np.testing.assert_allclose(d, [0.0, 0.25], atol=1e-5)


def test_trajectory_radius():
    c = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    assert trajectory_radius(c) == pytest.approx(1.0)


# ----------------------------------------------------------------------------- aggregation

T975 = {2: 4.302652729749464, 4: 2.7764451051977934}  # t quantiles 0.975 for dof 2 and 4


def test_t_interval_against_float64_reference():
    x = np.array([20.1, 21.7, 19.4], np.float64)
    mean, hw, k = t_interval(x)
    ref_sd = math.sqrt(sum((v - x.sum() / 3) ** 2 for v in x) / 2)
    assert k == 3
    assert mean == pytest.approx(x.sum() / 3, rel=1e-15)
    assert hw == pytest.approx(T975[2] * ref_sd / math.sqrt(3), rel=1e-12)
    assert t_interval([5.0, np.nan]) [:2] == (5.0, pytest.approx(math.nan, nan_ok=True))
    assert t_interval([])[2] == 0


def test_welch_interval_against_float64_reference():
    """Unpaired difference with Welch's degrees of freedom, against the formulas written out
    (3 and 5 samples: df = 2.38..., the t quantile taken from scipy at that df)."""
    from scipy.stats import t

    from evaluation.study.stats import welch_interval

    a, b = [20.76, 19.52, 19.91], [20.06, 19.26, 19.78, 19.94, 20.17]
    ma, mb = sum(a) / 3, sum(b) / 5
    va = sum((v - ma) ** 2 for v in a) / 2 / 3
    vb = sum((v - mb) ** 2 for v in b) / 4 / 5
    df = (va + vb) ** 2 / (va ** 2 / 2 + vb ** 2 / 4)
    diff, hw, got_df = welch_interval(a, b)
    assert diff == pytest.approx(ma - mb, rel=1e-14) and got_df == pytest.approx(df, rel=1e-12)
    assert hw == pytest.approx(t.ppf(0.975, df) * math.sqrt(va + vb), rel=1e-12)
    assert math.isnan(welch_interval([1.0], [1.0, 2.0])[1]) and welch_interval([1.0, 1.0], [2.0, 2.0])[1] == 0.0
    assert math.isnan(welch_interval([], [1.0, 2.0])[0])


def _runs() -> pd.DataFrame:
    rows = []
    for seed, (g, u) in enumerate([(20.0, 19.0), (21.0, 19.5), (22.0, 20.5), (20.5, 20.0), (21.5, 20.0)]):
        for mode, psnr in (("gated", g), ("uniform", u)):
            rows.append({"dataset": "d", "scene": "s", "n": 3, "cell": "zero", "bridge_mode": mode,
                         "seed": seed, "psnr": psnr, "ssim": 0.5, "lpips": 0.3, "floater_final": 0.1})
    return pd.DataFrame(rows)


def test_summarise_and_paired_differences_known_numbers():
    runs = _runs()
    s = summarise(runs, measures=("psnr",)).set_index("bridge_mode")
    assert s.loc["gated", "psnr_mean"] == pytest.approx(21.0)
    sd = np.std([20.0, 21.0, 22.0, 20.5, 21.5], ddof=1)
    assert s.loc["gated", "psnr_hw"] == pytest.approx(T975[4] * sd / math.sqrt(5), rel=1e-12)
    assert s.loc["gated", "psnr_k"] == 5
    d = paired_differences(runs, "gated", "uniform", measures=("psnr", "ssim")).iloc[0]
    diffs = np.array([1.0, 1.5, 1.5, 0.5, 1.5])
    assert d["psnr_mean"] == pytest.approx(diffs.mean())
    assert d["psnr_hw"] == pytest.approx(T975[4] * diffs.std(ddof=1) / math.sqrt(5), rel=1e-12)
    assert d["ssim_mean"] == 0.0 and d["ssim_hw"] == 0.0


# ----------------------------------------------------------------------------- report


def _fake_study_tree(root, cells=("zero", "rot_deg-2"), seeds=(0, 1, 2), modes=("gated", "uniform", "filtered"),
                     along_run=False, init="oracle", scene="bundled", n=3, coverage=False):
    """A study tree with the files the report reads (metrics, floaters, training log)."""
    import json

    rng = np.random.default_rng(0)
    for cell in cells:
        for s in seeds:
            run = root / cell / f"s{s}" / "synthetic" / scene / f"n{n}" / init
            run.mkdir(parents=True)
            (run / "status.json").write_text(json.dumps({"success_paper": True, "registered": 3, "noise": {}}))
            (run / "pose.json").write_text(json.dumps({"ate_pct_radius": 1.0 + s, "rel_rot_err_mean_deg": 0.5}))
            for m in modes:
                d = run / m
                (d / "train").mkdir(parents=True)
                (d / "metrics.json").write_text(json.dumps(
                    {"psnr": 20 + rng.normal(), "ssim": 0.5, "lpips_alex": 0.3, "n_images": 3,
                     **({"covered_alpha": 0.5, "coverage": 0.6 + 0.01 * s,
                         "covered": {"psnr": 25.0 + s, "ssim": 0.7, "lpips_alex": 0.2, "lpips_vgg": None}}
                        if coverage else {})}))
                if init == "oracle":  # no floater measure without a ground-truth mesh
                    (d / "floaters.json").write_text(json.dumps(
                        {"tau": 0.1, "seed": {"floater_frac": 0.2}, "final": {"floater_frac": 0.3 + 0.01 * s}}))
                (d / "train" / "train.json").write_text(json.dumps({"num_gaussians": 100 + s, "iterations": 20}))
                lg = {"iteration": [10, 20], "wall_time_s": [1.0, 2.0], "test_psnr": [19.0, 20.0],
                      "num_gaussians": [90, 100]}
                if along_run:  # SSIM best at 10, LPIPS best (lowest) at 20
                    lg.update(test_ssim=[0.6 + 0.01 * s, 0.55], test_lpips=[0.4, 0.35 - 0.01 * s])
                pd.DataFrame(lg).to_parquet(d / "train" / "log.parquet")


def test_run_study_reports_every_mode_with_an_interval(tmp_path):
    from evaluation.reports.report import _study_section
    from evaluation.study.report import run_study

    _fake_study_tree(tmp_path / "study")
    cells = expand_cells({"axes": [{"param": "rot_deg", "levels": [2]}]})
    md = run_study(tmp_path / "study", tmp_path / "study" / "report", cells).read_text()
    assert "| cell | gated | uniform | filtered |" in md
    assert "gated − uniform (paired by seed)" in md and "filtered − uniform" in md
    psnr = md.split("PSNR (final) [dB]")[1].split("##")[0]
    rows = [r for r in psnr.splitlines() if r.startswith("| zero") or r.startswith("| rot_deg-2")]
    assert len(rows) == 2 and all(r.count("±") == 3 for r in rows)
    assert "never VGGT" in md
    plots = sorted(p.name for p in (tmp_path / "study" / "report" / "plots").iterdir())
    assert plots == ["synthetic__bundled__n3__axis_rot_deg__zero.png", "synthetic__bundled__n3__psnr_vs_time.png"]
    # a log without SSIM / LPIPS along the run (older runs): no such tables, no error
    assert "coverage (final)" not in md and "PSNR covered" not in md  # metrics.json scored without alpha
    assert "SSIM (best it." not in md and "held-out LPIPS" not in md and "held-out PSNR [dB] along the run" in md
    # the regular HTML report embeds the section with its plots
    images = tmp_path / "images"
    images.mkdir()
    section = "".join(_study_section(tmp_path, images))
    assert "Initialisation study" in section and 'src="images/study/' in section
    assert (images / "study" / plots[0]).is_file()


def test_study_cli_reports_only_the_planned_grid(tmp_path, capfd):
    """Runs of an earlier grid left in the same tree (other n, seed or cell, e.g. an
    interrupted run of another config) are not mixed into the report's intervals."""
    import json

    from evaluation.__main__ import main

    root = tmp_path / "study"
    _fake_study_tree(root)                                   # the grid: n = 3, seeds 0-2
    _fake_study_tree(root, seeds=(0,), n=6)                  # an earlier partial n = 6 run
    _fake_study_tree(root, cells=("zero",), seeds=(7,))      # a seed the grid does not plan
    _fake_study_tree(root, cells=("trans_frac-0.1",), seeds=(0,))  # a cell it does not plan
    cells = expand_cells({"axes": [{"param": "rot_deg", "levels": [2]}]})
    args = ["study", "--results", str(root), "--cells", json.dumps(cells)]
    assert main(args + ["--out", str(tmp_path / "planned"), "--seeds", "0", "1", "2", "--views", "3"]) == 0
    runs = pd.read_csv(tmp_path / "planned" / "runs.csv")
    assert sorted(runs["n"].unique()) == [3] and sorted(runs["seed"].unique()) == [0, 1, 2]
    assert sorted(runs["cell"].unique()) == ["rot_deg-2", "zero"] and len(runs) == 2 * 3 * 3
    assert "left out 12 run folders" in capfd.readouterr().err
    md = (tmp_path / "planned" / "study.md").read_text()
    assert "n = 6" not in md and "| zero |" in md
    # without a plan (the report alone on a tree) every run found is reported, as before
    assert main(["study", "--results", str(root), "--out", str(tmp_path / "all")]) == 0
    assert len(pd.read_csv(tmp_path / "all" / "runs.csv")) == 18 + 12


def test_run_study_reports_ssim_and_lpips_at_the_best_iteration_and_along_the_run(tmp_path):
    from evaluation.study.report import run_study

    _fake_study_tree(tmp_path / "study", along_run=True)
    cells = expand_cells({"axes": [{"param": "rot_deg", "levels": [2]}]})
    md = run_study(tmp_path / "study", tmp_path / "study" / "report", cells).read_text()
    # best = highest SSIM (iteration 10), lowest LPIPS (iteration 20); mean over seeds 0, 1, 2
    ssim = md.split("SSIM (best it.: highest)")[1].split("##")[0]
    assert "| zero | 0.610 ± 0.025 | 0.610 ± 0.025 | 0.610 ± 0.025 |" in ssim
    assert "| zero | 10 ± 0 |" in md.split("best SSIM iteration [it.]")[1].split("##")[0]
    lpips = md.split("LPIPS (best it.: lowest)")[1].split("##")[0]
    assert "| zero | 0.340 ± 0.025 |" in lpips
    assert "| zero | 20 ± 0 |" in md.split("best LPIPS iteration [it.]")[1].split("##")[0]
    # along the run: only the point cells (zero here), a column per evaluation iteration
    along = md.split("held-out LPIPS-alex along the run (lower is better)")[1].split("##")[0]
    assert "| cell | mode | it. 10 | it. 20 | training time at the last [s] |" in along
    assert "| zero | gated | 0.400 ± 0.000 | 0.340 ± 0.025 | 2.0 |" in along
    assert "rot_deg-2" not in along
    assert "held-out SSIM along the run (higher is better)" in md
    plots = sorted(p.name for p in (tmp_path / "study" / "report" / "plots").iterdir())
    assert {"synthetic__bundled__n3__ssim_vs_time.png", "synthetic__bundled__n3__lpips_vs_time.png"} <= set(plots)
    curves = pd.read_csv(tmp_path / "study" / "report" / "curves.csv")
    assert len(curves) == 2 * 3 * 3 * 2 and {"test_ssim", "test_lpips", "wall_time_s"} <= set(curves)


def _fake_colmap_run(root, n, ok):
    """A regular COLMAP run folder R/synthetic/bundled/n{n}/colmap: trained (uniform) when it
    succeeded, only status.json when it failed (what the workflow leaves)."""
    import json

    run = root / "synthetic" / "bundled" / f"n{n}" / "colmap"
    run.mkdir(parents=True)
    (run / "status.json").write_text(json.dumps(
        {"success_paper": ok, "aligned_ok": ok, "registered": n if ok else 0, "n_images": n, "points": 50 if ok else 0,
         "reason": None if ok else "no model: the incremental mapper found no initial image pair"}))
    if ok:
        (run / "pose.json").write_text(json.dumps({"ate_pct_radius": 15.8, "rel_rot_err_mean_deg": 11.9}))
        d = run / "uniform"
        (d / "train").mkdir(parents=True)
        (d / "metrics.json").write_text(json.dumps({"psnr": 14.54, "ssim": 0.31, "lpips_alex": 0.52, "n_images": 3}))
        (d / "train" / "train.json").write_text(json.dumps({"num_gaussians": 700, "iterations": 20}))
        pd.DataFrame({"iteration": [10, 20], "wall_time_s": [1.0, 2.0], "test_psnr": [15.0, 14.6],
                      "test_ssim": [0.33, 0.31], "test_lpips": [0.55, 0.52], "num_gaussians": [600, 700]}).to_parquet(
            d / "train" / "log.parquet")
    return run


def test_run_study_reports_colmap_as_a_reference_row_and_a_failure_as_a_result(tmp_path):
    from evaluation.__main__ import main
    from evaluation.study.report import run_study

    _fake_study_tree(tmp_path / "study", along_run=True)
    ok = _fake_colmap_run(tmp_path, 3, True)
    cells = expand_cells({"axes": [{"param": "rot_deg", "levels": [2]}]})
    md = run_study(tmp_path / "study", tmp_path / "report", cells, references=[ok]).read_text()
    table = md.split("n = 3: reference initialisers (one regular run each, no seeds)")[1].split("##")[0]
    assert "| colmap | uniform | yes (3/3 registered) | 15.80 | 11.90 | 14.54 | 15.00 | 0.310 | 0.330 | 0.520 | " \
           "0.520 | 700 |" in table
    assert "COLMAP has no confidence" in md
    # a failed COLMAP (nothing trained) is a row that says so, through the CLI as the workflow calls it
    failed = _fake_colmap_run(tmp_path / "other", 3, False)
    assert main(["study", "--results", str(tmp_path / "study"), "--out", str(tmp_path / "report2"),
                 "--reference", str(ok), "--reference", str(failed)]) == 0
    md = (tmp_path / "report2" / "study.md").read_text()
    rows = [r for r in md.splitlines() if r.startswith("| colmap |")]
    assert len(rows) == 2
    assert rows[1].startswith("| colmap | - | no: no model: the incremental mapper found no initial image pair "
                              "(0/3) | -")
    refs = pd.read_csv(tmp_path / "report2" / "references.csv")
    assert list(refs["success_paper"]) == [True, False]


def test_run_study_reads_posed_cells(tmp_path):
    """The real-scene arm's tree: posed cells, mode uniform only, no floaters.json."""
    from evaluation.study.report import run_study

    _fake_study_tree(tmp_path / "study", modes=("uniform",), init="posed", scene="fern", along_run=True)
    cells = expand_cells({"axes": [{"param": "rot_deg", "levels": [2]}]})
    md = run_study(tmp_path / "study", tmp_path / "report", cells).read_text()
    assert "posed initialiser" in md and "never VGGT" in md and "oracle (ground truth" not in md
    assert "| cell | uniform |" in md and "floater frac." not in md and "− uniform" not in md
    assert "synthetic/fern, n = 3: SSIM (best it.: highest)" in md
    runs = pd.read_csv(tmp_path / "report" / "runs.csv")
    assert set(runs["init"]) == {"posed"} and len(runs) == 6


def test_run_study_reports_coverage_and_covered_psnr_where_scored_with_alpha(tmp_path):
    from evaluation.study.report import run_study

    _fake_study_tree(tmp_path / "study", coverage=True)
    cells = expand_cells({"axes": [{"param": "rot_deg", "levels": [2]}]})
    md = run_study(tmp_path / "study", tmp_path / "study" / "report", cells).read_text()
    cov = md.split("coverage (final) [fraction]")[1].split("##")[0]
    assert "| zero | 0.610 ± " in cov  # mean over seeds 0, 1, 2 of 0.6 + 0.01 s
    covered = md.split("PSNR covered (final) [dB]")[1].split("##")[0]
    assert "| zero | 26.00 ± " in covered
