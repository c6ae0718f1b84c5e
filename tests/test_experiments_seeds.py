"""experiments/sparse_views/seeds.py: a pre-registered seed comparison read from records, and the
benchmark cell's choice of seed (experiments/sparse_views/cells.py)."""

from __future__ import annotations

import json
import shlex

import pytest
import yaml

from experiments.sparse_views import cells, seeds

REG = {"name": "t", "role": "evaluation", "scenes": ["a", "b", "c"], "n": 3, "seeds": [0, 1], "iterations": 10,
       "variants": {"paper": {"recipe": "paper"}, "paper-mvs": {"recipe": "paper", "init": "mvs", "bridge_mode": "gated"}},
       "targets": [{"better": "paper-mvs", "than": "paper", "by": 1.0}]}


def _record(root, scene, variant, seed, psnr):
    run = root / "runs" / f"{scene}_n3_{variant}_s{seed}_i10.json"
    run.parent.mkdir(parents=True, exist_ok=True)
    run.write_text(json.dumps({"psnr": psnr, "ssim": 0.5, "lpips_alex": 0.4, "lpips_vgg": 0.5, "gaussians": 10,
                               "seed_gaussians": 5, "curve": {"coverage": [0.9], "psnr_covered": [psnr + 1]}}))


def test_the_report_pairs_by_seed_takes_the_scene_as_the_unit_and_gives_verdicts(tmp_path):
    gains = {"a": 2.0, "b": 1.0, "c": 3.0}
    for scene, gain in gains.items():
        for seed in (0, 1):
            _record(tmp_path, scene, "paper", seed, 15.0 + seed)
            _record(tmp_path, scene, "paper-mvs", seed, 15.0 + seed + gain)
    rep = seeds.report(REG, tmp_path, None)
    (c,) = rep["comparisons"]
    assert rep["runs"] == rep["runs_expected"] == 12 and rep["complete_scenes"] == ["a", "b", "c"]
    assert c["psnr_diff_per_scene"] == pytest.approx(gains) and c["psnr_diff"]["mean"] == pytest.approx(2.0)
    assert c["psnr_diff"]["k"] == 3 and c["psnr_diff"]["lo"] < 2.0 < c["psnr_diff"]["hi"]
    assert c["met"] and c["scenes_ahead"] == 3
    # a scene without all its runs is left out, and the verdict is "incomplete", not "met"
    (tmp_path / "runs" / "c_n3_paper-mvs_s1_i10.json").unlink()
    rep = seeds.report(REG, tmp_path, None)
    assert rep["complete_scenes"] == ["a", "b"] and not rep["comparisons"][0]["met"]
    assert "| incomplete |" in seeds.markdown(rep, "reg.yaml", "cmd")


def test_the_run_command_names_every_variant_and_the_registration_is_checked(tmp_path):
    cmd = shlex.split(seeds.run_command(REG, "W"))
    assert cmd[:4] == ["python", "-m", "experiments.sparse_views", "run"] and "paper" in cmd
    assert 'paper-mvs={"recipe":"paper","init":"mvs","bridge_mode":"gated"}' in cmd
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({**REG, "targets": [{"better": "paper-x", "than": "paper", "by": 1}]}))
    with pytest.raises(ValueError, match="'paper-x' is not a variant"):
        seeds.load_registration(bad)
    assert seeds.load_registration(seeds.DEFAULT_REGISTRATION)["n"] == 3  # the shipped one reads
    # a registration with its own records folder: the run line writes there and the report reads there
    own = {**REG, "records": "experiments/records/own_set"}
    cmd = shlex.split(seeds.run_command(own, "W"))
    assert cmd[3:6] == ["--records", "experiments/records/own_set", "run"]
    assert seeds.records_dir(own) == seeds.REPO / "experiments" / "records" / "own_set"
    assert seeds.records_dir(REG) == seeds.RECORDS
    for bad_rec in ("/tmp/x", "../x", 3):
        bad.write_text(yaml.safe_dump({**REG, "records": bad_rec}))
        with pytest.raises(ValueError, match="'records' is a folder inside the repository"):
            seeds.load_registration(bad)


def test_a_cell_seed_is_a_known_initialiser():
    assert cells.seed_folder() == "" and cells.seed_folder("mvs", "uniform") == "seed_mvs_uniform"
    with pytest.raises(ValueError, match="unknown seed initialiser"):
        cells.seed_folder("vggt")
    with pytest.raises(ValueError, match="no confidence"):
        cells.seed_folder("random", "gated")
    assert cells.seed_folder("mvs", "gated", 4) == "seed_mvs_gated_stride4"
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="stride is an integer >= 1"):
            cells.seed_folder("mvs", "gated", bad)
    with pytest.raises(ValueError, match="stride is an integer >= 1"):
        cells.seed_folder("random", None, 2)
    # the initialiser's own flags name the folder its run shares with every Bridge choice
    assert cells.seed_folder("mvs", "uniform", None, {"fill_stride": 0}) == "seed_mvs_fill_stride0_uniform"
    for bad in ({"fill stride": 0}, {"fill_stride": "../x"}, {"fill_stride": [1]}):
        with pytest.raises(ValueError, match="init_args"):
            cells.seed_folder("mvs", None, None, bad)
    with pytest.raises(ValueError, match="no init_args"):
        cells.seed_folder("posed", None, None, {"fill_stride": 0})


def test_a_target_against_the_floor_and_its_conditions_decide_the_verdict(tmp_path, monkeypatch):
    """`than: floor` reads the flat mean-colour image's PSNR per scene; `interval_above_zero` and
    `lpips_no_worse` must hold beside the mean difference for a target to be met."""
    floors = {"a": 12.0, "b": 13.0, "c": 14.0}
    monkeypatch.setattr(seeds, "floor_psnr", lambda cell: floors[cell.name.split("_n")[0]])
    reg = {**REG, "targets": [{"better": "paper-mvs", "than": "floor", "by": 3.0},
                              {"better": "paper-mvs", "than": "paper", "by": 0.5, "interval_above_zero": True},
                              {"better": "paper-mvs", "than": "paper", "by": 0.5, "lpips_no_worse": True}]}
    gains = {"a": 2.0, "b": -1.0, "c": 2.5}  # mean +1.17, interval spanning 0
    for scene, gain in gains.items():
        for seed in (0, 1):
            _record(tmp_path, scene, "paper", seed, 15.0)
            _record(tmp_path, scene, "paper-mvs", seed, 15.0 + gain)
    rep = seeds.report(reg, tmp_path, tmp_path / "work")
    floor_c, interval_c, lpips_c = rep["comparisons"]
    assert floor_c["psnr_diff_per_scene"] == pytest.approx({s: 15.0 + gains[s] - floors[s] for s in gains})
    assert floor_c["met"] and floor_c["lpips_alex_diff"] is None  # mean +3.83 dB over the floor
    assert interval_c["psnr_diff"]["lo"] < 0 and not interval_c["met"]  # the mean alone would pass
    assert lpips_c["met"]  # equal LPIPS is no worse
    for scene in gains:  # a worse LPIPS on every scene fails the same comparison
        (tmp_path / "runs" / f"{scene}_n3_paper-mvs_s0_i10.json").write_text(json.dumps(
            {"psnr": 15.0 + gains[scene], "ssim": 0.5, "lpips_alex": 0.6, "lpips_vgg": 0.5, "gaussians": 10,
             "seed_gaussians": 5, "curve": {"coverage": [0.9], "psnr_covered": [16.0]}}))
    assert not seeds.report(reg, tmp_path, tmp_path / "work")["comparisons"][2]["met"]
    page = seeds.markdown(rep, "reg.yaml", "cmd")
    assert "| paper-mvs - floor |" in page and ">= +0.5 dB, interval above 0 |" in page
    assert ">= +0.5 dB, LPIPS no worse |" in page
    bad = tmp_path / "bad.yaml"
    for target, needle in (({"better": "floor", "than": "paper", "by": 1}, "'floor' is not a variant"),
                           ({"better": "paper-mvs", "than": "paper", "by": 1, "above": True}, "unknown target keys")):
        bad.write_text(yaml.safe_dump({**REG, "targets": [target]}))
        with pytest.raises(ValueError, match=needle):
            seeds.load_registration(bad)


def test_a_comparison_on_scenes_a_registration_measured_says_it_is_not_on_unseen_scenes(tmp_path):
    """Its values may be fixed before its runs, but the scenes are not unseen: the report names the
    pre-registered set that measured them first, and the page says the figures are not
    pre-registered results; the shipped re-measurements are caught, the registrations are not."""
    fill = seeds.load_registration(seeds.REGISTERED / "mvs_fill_seed.yaml")
    reg = {**REG, "scenes": [fill["scenes"][0], "elsewhere"]}
    for seed in (0, 1):
        for scene in reg["scenes"]:
            _record(tmp_path, scene, "paper", seed, 15.0)
            _record(tmp_path, scene, "paper-mvs", seed, 16.0)
    rep = seeds.report(reg, tmp_path, None)
    assert rep["scenes_measured_before"] == {"mvs_fill_seed": [fill["scenes"][0]]}
    assert "Not an evaluation on unseen scenes: `mvs_fill_seed` measured 1 of the 2 before" in seeds.markdown(
        rep, "reg.yaml", "cmd")
    assert "scenes_measured_before" not in seeds.report(REG, tmp_path, None)
    for path in sorted((seeds.HERE / "remeasured").glob("*.yaml")):
        assert seeds.measured_before(seeds.load_registration(path), path), path.name
    for path in sorted(seeds.REGISTERED.glob("*.yaml")):
        assert seeds.measured_before(seeds.load_registration(path), path) == {}, path.name
