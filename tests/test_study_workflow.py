"""Dry runs of the initialisation study's configs: the grid expands into the expected jobs
(cells x seeds x view counts x Bridge modes), and a config without `study:` plans none."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from evaluation.study.grid import expand_cells
from test_workflow_dryrun import REPO, SNAKEMAKE, dry_run, jobs, synth_config

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")

STUDY_RULES = ("study_oracle", "study_pose_eval", "study_bridge", "study_align", "study_train",
               "study_render", "study_metrics", "study_floaters")


@pytest.mark.parametrize("name", ["init_study_quick.yaml", "init_study.yaml"])
def test_study_config_plans_the_grid(tmp_path, name):
    cfg = yaml.safe_load((REPO / "config" / name).read_text())
    cfg["results"] = "results"
    counts, out = dry_run(tmp_path, cfg)
    cells = expand_cells(cfg["study"])
    runs = len(cells) * len(cfg["study"]["seeds"]) * len(cfg["views"])
    modes = len(cfg["bridge"]["modes"])
    assert jobs(counts, "study_oracle") == runs
    assert jobs(counts, "study_pose_eval") == runs
    for rule in STUDY_RULES[2:]:
        assert jobs(counts, rule) == runs * modes, rule
    assert jobs(counts, "study_report") == 1
    assert "vggt_like_sim" in cells and "zero" in cells
    for cell in cells:
        assert f"results/study/{cell}/s0/synthetic/bundled/n3/oracle/gated/floaters.json" in out
    # the study section waits for the study: the report comes after it
    assert jobs(counts, "report") == 1
    # COLMAP as a reference row: the regular COLMAP run of every n, then the report (its
    # trained stages are planned after the colmap_index checkpoint: a failure stops there)
    assert cfg["study"]["references"] == ["colmap"]
    assert jobs(counts, "colmap_baseline") == len(cfg["views"]) and jobs(counts, "colmap_index") == 1
    report = out.split("rule study_report:")[1]
    for n in cfg["views"]:
        assert f"--reference results/synthetic/bundled/n{n}/colmap" in report
    # the report reads only the planned grid, never other runs left in the tree
    plan = " ".join(str(x) for x in cfg["study"]["seeds"]), " ".join(str(n) for n in sorted(cfg["views"]))
    assert f"--seeds {plan[0]} --views {plan[1]}" in report


def test_no_study_section_plans_no_study_jobs(tmp_path):
    counts, _ = dry_run(tmp_path, synth_config(initialisers=["oracle"]))
    assert all(jobs(counts, rule) == 0 for rule in STUDY_RULES + ("study_report",))
    assert jobs(counts, "train_splats") > 0


def test_study_axis_with_an_unknown_param_is_a_config_error(tmp_path):
    cfg = synth_config(initialisers=["oracle"], study={"seeds": [0], "axes": [{"param": "focal", "levels": [1]}]})
    _, out = dry_run(tmp_path, cfg, expect_ok=False)
    assert "focal" in out


def test_study_reference_must_be_a_configured_initialiser(tmp_path):
    cfg = synth_config(initialisers=["oracle"], study={"seeds": [0], "references": ["colmap"]})
    _, out = dry_run(tmp_path, cfg, expect_ok=False)
    assert "study.references ['colmap'] must also be in `initialisers`" in out


def test_study_without_references_plans_no_colmap(tmp_path):
    cfg = synth_config(initialisers=["oracle"], views=[3], study={"seeds": [0]})
    counts, out = dry_run(tmp_path, cfg)
    assert jobs(counts, "study_report") == 1 and jobs(counts, "colmap_baseline") == 0
    assert "--reference" not in out


def test_real_scene_arm_plans_posed_cells_without_shared_data(tmp_path):
    """config/init_study_fern.yaml's blocks on a generated posed scene (images + reference
    cameras, no ground-truth mesh) instead of LLFF fern: posed cells in mode uniform,
    no oracle, no floaters, the cell's pose noise and seed on the posed command line."""
    from _workflow_run import posed_source as _posed_source

    _posed_source(tmp_path)
    cfg = yaml.safe_load((REPO / "config" / "init_study_fern.yaml").read_text())
    cfg["results"] = "results"
    cfg["datasets"] = {"real": {"scenes": {"posedscene": {"path": "posed_src"}}}}
    counts, out = dry_run(tmp_path, cfg)
    cells = expand_cells(cfg["study"])
    runs = len(cells) * len(cfg["study"]["seeds"])
    assert cfg["study"]["initialiser"] == "posed" and len(cells) == 9
    assert jobs(counts, "study_posed") == runs and jobs(counts, "study_pose_eval") == runs
    for rule in ("study_bridge", "study_align", "study_train", "study_render", "study_metrics"):
        assert jobs(counts, rule) == runs, rule  # one Bridge mode: uniform
    assert jobs(counts, "study_oracle") == 0 and jobs(counts, "study_floaters") == 0
    assert jobs(counts, "study_report") == 1 and jobs(counts, "colmap_baseline") == 1
    assert "results/study/rot_deg-2/s1/real/posedscene/n3/posed/uniform/metrics.json" in out
    assert "--rot-deg 2.0 --trans-frac 0.0 --depth-rel 0.0 --outlier-frac 0.0 --seed 1" in out
    assert "--eval-lpips" in out and "--reference results/real/posedscene/n3/colmap" in out


def test_posed_study_refuses_confidence_axes(tmp_path):
    cfg = synth_config(initialisers=["oracle"], views=[3],
                       study={"seeds": [0], "initialiser": "posed",
                              "axes": [{"param": "conf_mode", "levels": ["anti"]}]})
    _, out = dry_run(tmp_path, cfg, expect_ok=False)
    assert "has no confidence" in out and "conf_mode-anti" in out
