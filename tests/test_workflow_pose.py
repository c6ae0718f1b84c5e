"""Dry runs with the camera-refinement switches: training-time pose refinement
(train.pose_refine) plans the refined alignment and renders with it."""

from __future__ import annotations

import re

from test_workflow_dryrun import SNAKEMAKE, dry_run, jobs, synth_config  # noqa: F401 (skip marker)

import pytest

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")


def test_pose_refinement_switch(tmp_path):
    (tmp_path / "off").mkdir()
    (tmp_path / "on").mkdir()
    off, out_off = dry_run(tmp_path / "off", synth_config(views=[3], initialisers=["oracle"]))
    assert jobs(off, "align_refined_cameras") == 0 and "--pose-refine" not in out_off
    on, out = dry_run(tmp_path / "on", synth_config(views=[3], initialisers=["oracle"],
                                                    train={"iterations": 10, "pose_refine": True}))
    assert jobs(on, "train_splats") == 1 and jobs(on, "align_refined_cameras") == 1
    assert jobs(on, "align_test_cameras") == 1  # still feeds the held-out curve during training
    assert re.search(r"python -m splat_train .*--pose-refine(?! --pose-refine-focal)", out)
    assert re.search(r"evaluation align --pred \S+/train/cameras_refined --train-cameras refined", out)
    assert re.search(r"splat_train render .*--cameras \S+/align_refined/sparse/0", out)


def test_bundle_adjusted_initialisers(tmp_path):
    cfg = synth_config(views=[3], initialisers=["oracle", "oracle_ba", "posed_ba", "vggt_ba"],
                       ba={"refine_focal": True})
    counts, out = dry_run(tmp_path, cfg)
    assert jobs(counts, "ba_predictions") == 2 and jobs(counts, "ba_posed") == 1
    assert jobs(counts, "oracle_init") == 1 and jobs(counts, "posed_init") == 1 and jobs(counts, "vggt_init") == 1
    # every refined initialiser is evaluated and trained like the others
    assert jobs(counts, "pose_eval") == 4 and jobs(counts, "train_splats") == 4
    assert jobs(counts, "bridge_predictions") == 3 and jobs(counts, "bridge_colmap") == 1
    assert re.search(r"evaluation\.initialisers\.ba_init --init \S+/n3/posed --images .*--seed-points triangulated", out)
    assert re.search(r"evaluation\.initialisers\.ba_init --init \S+/n3/vggt --images .*--refine-focal", out)
    assert "--min-points" not in out  # null: the step's own default
