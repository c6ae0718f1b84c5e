"""Dry runs of the Snakemake workflow on configs that differ in what a scene needs: only
the jobs that apply are planned. Also: config schema errors name the key, the SLURM profiles
ask for a GPU only where the device is CUDA, CPUs = threads, and command-line overrides
keep the rules' memory and runtime."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from vggt_init import defaults as vggt_defaults

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = shutil.which("snakemake")
# VGGT is planned as on a machine with its checkpoint (any existing file will do for a dry run);
# tests/test_workflow_no_checkpoint.py plans and runs without one.
WITH_CHECKPOINT = {**os.environ, "VGGT_CHECKPOINT": str(REPO / "tests" / "data" / "vggt" / "shared" / "weights.safetensors")}

pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")


def _write_colmap_source(root: Path, model: str, params: str) -> Path:
    """A tiny COLMAP text model (one camera, no images) as a source scene."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"1 {model} 64 48 {params}\n")
    (sparse / "images.txt").write_text("")
    (sparse / "points3D.txt").write_text("")
    (root / "images").mkdir()
    return root


def dry_run(tmp_path: Path, cfg: dict, *args: str, targets: tuple[str, ...] = (),
            expect_ok: bool = True) -> tuple[dict, str]:
    """Plan the workflow for ``cfg`` in ``tmp_path``.

    Returns:
        ({(rule, scene): job count} with scene None for rules without one, the output).
    """
    cfg_file = tmp_path / "config.yaml"
    cfg_file.write_text(yaml.safe_dump(cfg))
    cmd = [SNAKEMAKE, *targets, "-n", "-p", "--snakefile", str(REPO / "Snakefile"),
           "--directory", str(tmp_path), *args, "--configfile", str(cfg_file)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=WITH_CHECKPOINT)
    out = proc.stdout + proc.stderr
    if not expect_ok:
        assert proc.returncode != 0, out
        return {}, out
    assert proc.returncode == 0, out
    counts: dict = {}
    for block in re.split(r"\n(?=\[)", out):
        rule = re.search(r"^(?:rule|checkpoint|localrule) (\w+):", block, re.M)
        if not rule:
            continue
        scene = re.search(r"wildcards: .*?scene=([\w.-]+)", block)
        key = (rule.group(1), scene.group(1) if scene else None)
        counts[key] = counts.get(key, 0) + 1
    return counts, out


def jobs(counts: dict, rule: str, scene: str | None = None) -> int:
    """Jobs of ``rule`` (for one scene, or over all)."""
    return sum(v for (r, s), v in counts.items() if r == rule and (scene is None or s == scene))


def synth_config(**overrides) -> dict:
    cfg = {
        "results": "results",
        "datasets": {"synthetic": {"scenes": {"bundled": {"synth": {"views": 24, "width": 64}}}}},
        "views": [3, 6],
        "initialisers": ["vggt", "colmap", "oracle"],
        "train": {"iterations": 10},
    }
    cfg.update(overrides)
    return cfg


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """One dry run over scenes that differ in what they need (module-wide, it is slow-ish):

    * bundled: synthetic, reference cameras, test split, ground truth (everything applies);
    * photos: a bare image folder (no reference cameras: no pose or held-out stages, no oracle);
    * notest: synthetic with a manifest that has no test views (pose yes, held-out no);
    * dist / pin: COLMAP sources with a distorted / pinhole camera (undistort only the first).
    """
    tmp = tmp_path_factory.mktemp("mixed")
    (tmp / "photos").mkdir()
    _write_colmap_source(tmp / "dist", "SIMPLE_RADIAL", "50 32 24 0.01")
    _write_colmap_source(tmp / "pin", "PINHOLE", "50 50 32 24")
    manifest = tmp / "manifest.json"
    manifest.write_text(json.dumps({"test": [], "train": {"3": [f"{i:04d}.png" for i in range(3)]}}))
    cfg = synth_config(datasets={
        "synthetic": {"scenes": {
            "bundled": {"synth": {"views": 24, "width": 64}},
            "notest": {"synth": {"views": 8, "width": 64},
                       "split": {"rule": "manifest", "manifest": str(manifest)}, "views": [3]},
        }},
        "real": {"scenes": {
            "photos": {"path": "photos", "format": "folder"},
            "dist": {"path": "dist", "initialisers": ["colmap"]},
            "pin": {"path": "pin", "initialisers": ["colmap"]},
        }},
    })
    return dry_run(tmp, cfg)


def test_synthetic_scene_plans_every_stage(mixed):
    counts, out = mixed
    assert jobs(counts, "synth_scene", "bundled") == 1
    for rule in ("vggt_init", "colmap_baseline", "oracle_init", "train_list"):
        assert jobs(counts, rule, "bundled") == 2, rule
    # VGGT and the oracle are planned to the end; COLMAP's later jobs wait for its checkpoint
    for rule in ("pose_eval", "bridge_predictions", "align_test_cameras", "train_splats",
                 "render_test", "image_metrics"):
        assert jobs(counts, rule, "bundled") == 4, rule
    assert jobs(counts, "testpose_refine") == 0  # the test-pose protocol is off by default
    assert jobs(counts, "colmap_index") == 1 and jobs(counts, "test_images", "bundled") == 1
    assert jobs(counts, "tables") == jobs(counts, "plots") == jobs(counts, "report") == 1
    # the point head is used (vggt_init's default: no --points-from): the depth head is not asked for
    assert vggt_defaults.POINTS_FROM == "point_head" and "--points-from" not in out
    # VGGT asks for a GPU (resources gpu=1) and is told to use it when the job sees one; its
    # dtype is vggt_init's default (auto)
    vggt_cmds = [line for line in out.splitlines() if "python -m vggt_init" in line]
    assert vggt_cmds and all("--device auto " in c + " " and "--dtype" not in c for c in vggt_cmds), vggt_cmds
    # the COLMAP baseline is given every core snakemake has (recorded in status.json)
    assert re.search(r"evaluation\.initialisers\.colmap_baseline .*--threads [1-9]", out)


def test_floor_per_scene_and_view_count(mixed):
    """floor.json (the flat mean-colour image's held-out metrics) once per (scene, n) with
    held-out views, whatever the initialisers; none without reference cameras or test views."""
    counts, out = mixed
    assert jobs(counts, "floor", "bundled") == 2
    for n in (3, 6):
        assert f"output: results/synthetic/bundled/n{n}/floor.json" in out
    assert jobs(counts, "floor", "photos") == jobs(counts, "floor", "notest") == 0


def test_scene_without_reference_cameras(mixed):
    counts, _ = mixed
    assert jobs(counts, "convert_scene", "photos") == 1 and jobs(counts, "synth_scene", "photos") == 0
    for rule in ("pose_eval", "align_test_cameras", "render_test", "image_metrics", "test_images",
                 "oracle_init", "undistort_scene"):
        assert jobs(counts, rule, "photos") == 0, rule
    assert jobs(counts, "vggt_init", "photos") == 2 and jobs(counts, "train_splats", "photos") == 2


def test_manifest_without_test_views(mixed):
    counts, out = mixed
    assert "--manifest" in out
    assert jobs(counts, "pose_eval", "notest") == 2 and jobs(counts, "train_splats", "notest") == 2
    for rule in ("align_test_cameras", "render_test", "image_metrics", "test_images"):
        assert jobs(counts, rule, "notest") == 0, rule


def test_undistortion_only_for_distorted_data(mixed):
    counts, out = mixed
    assert jobs(counts, "undistort_scene", "dist") == 1 and jobs(counts, "convert_scene", "dist") == 0
    assert jobs(counts, "convert_scene", "pin") == 1 and jobs(counts, "undistort_scene", "pin") == 0
    assert re.search(r"camio convert --src dist .*--undistort", out)
    assert not re.search(r"camio convert --src pin .*--undistort", out)
    for scene in ("dist", "pin"):  # per-scene initialisers: COLMAP only
        assert jobs(counts, "colmap_baseline", scene) == 2
        assert jobs(counts, "vggt_init", scene) == jobs(counts, "oracle_init", scene) == 0


def test_no_colmap_no_training_and_the_depth_head(tmp_path):
    cfg = synth_config(initialisers=["vggt", "oracle"], vggt={"points_from": "depth"},
                       train={"enabled": False})
    counts, out = dry_run(tmp_path, cfg)
    assert jobs(counts, "colmap_baseline") == 0 and jobs(counts, "colmap_index") == 0
    assert "--points-from depth" in out
    for rule in ("bridge_predictions", "train_splats", "render_test", "image_metrics",
                 "align_test_cameras", "floor"):
        assert jobs(counts, rule) == 0, rule
    assert jobs(counts, "pose_eval") == 4 and jobs(counts, "tables") == 1


def test_testpose_protocol_switch(tmp_path):
    """evaluation.testpose: true plans the test-pose protocol beside the strict one for every
    run; false (the default) plans the strict protocol alone."""
    (tmp_path / "on").mkdir()
    (tmp_path / "off").mkdir()
    counts, out = dry_run(tmp_path / "on", synth_config(initialisers=["oracle"], views=[3],
                                                        evaluation={"testpose": True}))
    assert jobs(counts, "image_metrics") == jobs(counts, "testpose_refine") == jobs(counts, "testpose_metrics") == 1
    cmd = next(line for line in out.splitlines() if "splat_train testpose" in line)
    assert "--device auto" in cmd and "--steps" not in cmd and "--patience" not in cmd  # the CLI's defaults
    (tmp_path / "set").mkdir()
    counts, out = dry_run(tmp_path / "set", synth_config(initialisers=["oracle"], views=[3], train={"iterations": 10, "device": "cpu"},
                                                         evaluation={"testpose": True, "testpose_steps": 50,
                                                                     "testpose_patience": 10}))
    cmd = next(line for line in out.splitlines() if "splat_train testpose" in line)
    assert "--device cpu" in cmd and "--steps 50" in cmd and "--patience 10" in cmd
    counts, out = dry_run(tmp_path / "off", synth_config(initialisers=["oracle"], views=[3],
                                                         evaluation={"testpose": False}))
    assert jobs(counts, "image_metrics") == 1
    assert jobs(counts, "testpose_refine") == jobs(counts, "testpose_metrics") == 0


def test_snapshot_every_reaches_the_trainer_only_when_set(tmp_path):
    """train.snapshot_every N makes every training job replace train/snapshot.ply every N
    iterations (what the viewer follows live); null, the default, passes nothing."""
    (tmp_path / "on").mkdir()
    (tmp_path / "off").mkdir()
    _, out = dry_run(tmp_path / "on", synth_config(initialisers=["oracle"], views=[3],
                                                   train={"iterations": 10, "snapshot_every": 7}))
    cmd = next(line for line in out.splitlines() if "python -m splat_train --seed-ply" in line)
    assert "--snapshot-every 7 " in cmd + " "
    _, out = dry_run(tmp_path / "off", synth_config(initialisers=["oracle"], views=[3]))
    cmd = next(line for line in out.splitlines() if "python -m splat_train --seed-ply" in line)
    assert "--snapshot-every" not in cmd


def test_a_training_device_by_index_reaches_the_trainer(tmp_path):
    """train.device cuda:1 passes --device cuda:1 to every training job."""
    _, out = dry_run(tmp_path, synth_config(initialisers=["oracle"], views=[3],
                                            train={"iterations": 10, "device": "cuda:1"}))
    cmd = next(line for line in out.splitlines() if "python -m splat_train --seed-ply" in line)
    assert "--device cuda:1 " in cmd


def test_stage_target_and_per_scene_view_counts(tmp_path):
    cfg = synth_config()
    cfg["datasets"]["synthetic"]["scenes"]["bundled"]["views"] = [3]
    counts, _ = dry_run(tmp_path, cfg, targets=("inits",))
    assert jobs(counts, "vggt_init") == jobs(counts, "oracle_init") == jobs(counts, "colmap_baseline") == 1
    assert jobs(counts, "train_splats") == 0 and jobs(counts, "tables") == 0


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda c: c["datasets"]["synthetic"]["scenes"]["bundled"].update(colour="red"), "colour"),
        (lambda c: c["train"].update(iterations="many"), "iterations"),
    ],
)
def test_config_errors_name_the_key(tmp_path, mutate, message):
    cfg = synth_config()
    mutate(cfg)
    _, out = dry_run(tmp_path, cfg, expect_ok=False)
    assert "config error: " in out and message in out and "Traceback" not in out


def _resources(block: str) -> dict:
    """The ``resources:`` line of a dry-run job block as a dict of strings."""
    line = re.search(r"^\s*resources: (.*)$", block, re.M).group(1)
    return dict(kv.split("=", 1) for kv in line.split(", "))


def _threads(block: str) -> int:
    m = re.search(r"^\s*threads: (\d+)$", block, re.M)
    return int(m.group(1)) if m else 1


def _blocks(out: str, rule: str) -> list[str]:
    return [b for b in re.split(r"\n(?=\[)", out) if re.search(rf"^(?:rule|checkpoint) {rule}:", b, re.M)]


def _slurm_dry_run(tmp_path, profile: str, *args: str, cfg: dict | None = None):
    pytest.importorskip("snakemake_executor_plugin_slurm")
    # a dry run caps threads at --cores (1 by default); the SLURM executor has no cap
    return dry_run(tmp_path, cfg or synth_config(views=[3]), "--profile",
                   str(REPO / "workflow" / "profiles" / profile), "--cores", "64", *args)


def test_slurm_cpu_profile_asks_no_gpu_and_cpus_equal_threads(tmp_path):
    counts, out = _slurm_dry_run(tmp_path, "slurm", cfg=synth_config(views=[3], vggt={"threads": 4}))
    assert jobs(counts, "vggt_init") == 1 and jobs(counts, "train_splats") == 2
    shell_blocks = [b for b in re.split(r"\n(?=\[)", out) if re.search(r"^(?:rule|checkpoint) \w+:", b, re.M)
                    and "Shell command:" in b and "Shell command: None" not in b]  # targets run nothing
    assert shell_blocks
    for block in shell_blocks:
        res = _resources(block)
        assert res.get("gpu", "0") == "0", block
        assert int(res["cpus_per_task"]) == _threads(block), block
        assert int(res["runtime"]) > 0 and int(res["mem_mb"]) > 0, block
    assert _resources(_blocks(out, "vggt_init")[0])["cpus_per_task"] == "4"
    train = _resources(_blocks(out, "train_splats")[0])
    assert "--device auto" in out and "--resume-dir" in out
    # synth_config: 10 iterations -> the floor of 30 minutes; 6000 MB at <= 12 views
    assert train["runtime"] == "30" and train["mem_mb"] == "6000"


def test_slurm_gpu_profile_asks_a_gpu_for_vggt_and_training_only(tmp_path):
    counts, out = _slurm_dry_run(tmp_path, "slurm-gpu")
    for rule in ("vggt_init", "train_splats"):
        for block in _blocks(out, rule):
            res = _resources(block)
            assert res["gpu"] == "1" and res["slurm_partition"] == "gpu", block
            assert "--device cuda" in block
    for rule in ("colmap_baseline", "oracle_init", "image_metrics", "bridge_predictions"):
        for block in _blocks(out, rule):
            assert _resources(block).get("gpu", "0") == "0", block


def test_slurm_command_line_overrides_keep_the_rules_resources(tmp_path):
    """--default-resources / --set-resources / --set-threads on the command line replace the
    profile's blocks, but memory, runtime and CPUs live in the rules and stay."""
    _, out = _slurm_dry_run(tmp_path, "slurm", "--default-resources", "slurm_account=myproj",
                            "slurm_partition=short", "--set-resources", "train_splats:runtime=600",
                            "--set-threads", "synth_scene=2")
    colmap = _resources(_blocks(out, "colmap_baseline")[0])
    assert colmap["mem_mb"] == "8000" and colmap["runtime"] == "120"
    assert colmap["slurm_account"] == "myproj" and colmap["slurm_partition"] == "short"
    train = _resources(_blocks(out, "train_splats")[0])
    assert train["runtime"] == "600" and train["mem_mb"] == "6000"
    synth = _blocks(out, "synth_scene")[0]
    assert _threads(synth) == 2 and _resources(synth)["cpus_per_task"] == "2"


def test_cluster_resources_scale_with_views_and_resolution(tmp_path):
    cfg = synth_config(views=[24], vggt={"image_size": 518, "mem_mb": 12000, "runtime": 30},
                       train={"iterations": 20000, "mem_mb": 6000, "runtime": 180})
    _, out = dry_run(tmp_path, cfg)
    vggt = _resources(_blocks(out, "vggt_init")[0])
    assert vggt["mem_mb"] == "24000" and vggt["runtime"] == "60"  # 24 views = 2 x 12
    train = _resources(_blocks(out, "train_splats")[0])
    assert train["mem_mb"] == "12000" and train["runtime"] == str(180 * 2 * 2)
