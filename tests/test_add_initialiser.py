"""Adding an initialiser touches the registry and its own module only (docs/contracts.md,
"Adding an initialiser").

A copy of the project gets one initialiser more, ``refcams`` (the reference cameras and points
of the training views: a COLMAP model and status.json, the contract of the workflow's common
rule), by exactly two edits: its entry in evaluation/initialisers/registry.py and its module
evaluation/initialisers/refcams.py (the test checks that nothing else differs). Then, in the copy:

(a) the config check accepts ``initialisers: [refcams]`` and suggests it for a typo, where the
    project's own check refuses the name;
(b) the workflow plans its jobs (a dry run): the common rule runs its command on every view
    count, the Bridge seeds from its model in uniform mode, training and evaluation follow;
(c) the evaluation tables list its run, read from a small results tree in which the run folder
    is what its command wrote.
"""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from eval_fake_results import _mode_run, build, psnr_of

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = shutil.which("snakemake")
NAME = "refcams"

# The registry entry: a CPU command writing a COLMAP model and status.json, needing reference cameras.
ENTRY = (f'    Initialiser("{NAME}", "evaluation.initialisers.{NAME}", _MODEL, "status.json", False,\n'
         '                frozenset({"reference"})),\n')
# Its module: python -m evaluation.initialisers.refcams --scene S --image-list L --out D.
MODULE = '''"""The reference cameras and points of the training views, as an initialiser.

    python -m evaluation.initialisers.refcams --scene SCENE --image-list TRAIN_TXT --out DIR

Writes DIR/sparse/0 (COLMAP text) and DIR/status.json.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from runtime.atomic import write_json
from camio.colmap import read_model, write_text_model
from runtime.outdir import prepare_out, run_stage
from evaluation.initialisers.views import read_image_list

log = logging.getLogger(__name__)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.refcams")
    p.add_argument("--scene", required=True)
    p.add_argument("--image-list", required=True)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)

    def work() -> int:
        names = read_image_list(args.image_list)
        ref = read_model(Path(args.scene) / "sparse" / "0")
        cams = [c for c in ref.cameras if c.name in set(names)]
        out = prepare_out(args.out, {"--scene": args.scene, "--image-list": args.image_list},
                          "evaluation.refcams")
        write_text_model(out / "sparse" / "0", cams, ref.points, ref.colors)
        write_json(out / "status.json", {
            "success_paper": len(cams) == len(names), "aligned_ok": len(cams) >= 3, "registered": len(cams),
            "n_images": len(names), "points": len(ref.points), "reason": None, "wall_time_s": 0.0})
        return 0

    return run_stage(log, work)


if __name__ == "__main__":
    sys.exit(main())
'''


@pytest.fixture(scope="module")
def copy(tmp_path_factory) -> Path:
    """The project with ``refcams`` added: evaluation/ copied and edited, the rest linked."""
    root = tmp_path_factory.mktemp("added") / "repo"
    root.mkdir()
    for name in ("runtime", "camio", "imgmetrics", "vggt_init", "bridge", "splat_train", "workflow", "Snakefile",
                 "config.yaml"):
        (root / name).symlink_to(REPO / name)
    shutil.copytree(REPO / "evaluation", root / "evaluation", ignore=shutil.ignore_patterns("__pycache__"))
    registry = root / "evaluation" / "initialisers" / "registry.py"
    text = registry.read_text()
    anchor = "\n)}\nNAMES = tuple(INITIALISERS)"
    assert text.count(anchor) == 1, "the registry's list of initialisers moved: update ENTRY's anchor"
    registry.write_text(text.replace(anchor, "\n" + ENTRY.rstrip("\n") + anchor))
    (root / "evaluation" / "initialisers" / f"{NAME}.py").write_text(MODULE)
    return root


def _env(root: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(root), "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}


def _differences(a: Path, b: Path, rel: Path = Path()) -> set[str]:
    cmp = filecmp.dircmp(a, b, ignore=["__pycache__"])
    out = {str(rel / n) for n in cmp.left_only + cmp.right_only + cmp.diff_files + cmp.funny_files}
    for sub in cmp.common_dirs:
        out |= _differences(a / sub, b / sub, rel / sub)
    return out


def test_the_copy_differs_by_the_registry_and_the_module_only(copy):
    assert _differences(REPO / "evaluation", copy / "evaluation") == {
        "initialisers/registry.py", f"initialisers/{NAME}.py"}
    assert all((copy / n).is_symlink() for n in ("camio", "vggt_init", "bridge", "splat_train", "workflow"))
    code = f"from evaluation.initialisers import registry as r; i = r.get('{NAME}'); print(r.with_common_rule(), i.needs)"
    out = subprocess.run([sys.executable, "-c", code], cwd=copy, env=_env(copy), capture_output=True, text=True)
    assert out.stdout.strip() == f"('{NAME}',) frozenset({{'reference'}})", out.stderr


def _check(root: Path, cfg: dict, tmp_path: Path) -> subprocess.CompletedProcess:
    f = tmp_path / "config.yaml"
    f.write_text(yaml.safe_dump(cfg))
    return subprocess.run([sys.executable, "workflow/scripts/check_config.py", str(f)], cwd=root, env=_env(root),
                          capture_output=True, text=True, timeout=60)


def test_a_the_config_check_reads_the_name_from_the_registry(copy, tmp_path):
    base = yaml.safe_load((REPO / "config.yaml").read_text())
    ok = _check(copy, {**base, "initialisers": ["colmap", NAME]}, tmp_path)
    assert ok.returncode == 0, ok.stderr
    typo = _check(copy, {**base, "initialisers": ["refcam"]}, tmp_path)
    assert typo.returncode == 2 and f"'refcam' is not a valid value; did you mean '{NAME}'?" in typo.stderr
    before = _check(REPO, {**base, "initialisers": [NAME]}, tmp_path)  # the project without the entry
    assert before.returncode == 2 and f"initialisers.0: '{NAME}' is not a valid value" in before.stderr


def _dry_run(root: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    cfg = {"results": "results", "views": [3, 6], "initialisers": ["colmap", NAME], "train": {"iterations": 10},
           "datasets": {"synthetic": {"scenes": {"bundled": {"synth": {"views": 24, "width": 64}}}}}}
    tmp_path.mkdir()
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    return subprocess.run([SNAKEMAKE, "-n", "-p", "--snakefile", str(root / "Snakefile"), "--directory",
                           str(tmp_path), "--configfile", str(tmp_path / "config.yaml")],
                          env=_env(root), capture_output=True, text=True, timeout=180)


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_b_the_workflow_plans_its_jobs(copy, tmp_path):
    proc = _dry_run(copy, tmp_path / "added")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    blocks = out.split("\n\n")
    init_jobs = [b for b in blocks if "rule registry_init:" in b]
    assert len(init_jobs) == 2 and all(f"init={NAME}" in b for b in init_jobs), init_jobs
    for n in (3, 6):
        assert (f"python -m evaluation.initialisers.{NAME} --scene results/synthetic/bundled/synth "
                f"--image-list results/synthetic/bundled/n{n}/train.txt --out results/synthetic/bundled/n{n}/{NAME} ") in out
    for rule in ("bridge_colmap", "train_splats", "pose_eval", "image_metrics"):
        assert any(f"rule {rule}:" in b and f"init={NAME}" in b for b in blocks), rule
    assert f"n3/{NAME}/uniform/bridge/seed.ply" in out and f"n3/{NAME}/gated" not in out
    before = _dry_run(REPO, tmp_path / "project")  # the project without the entry refuses the config
    assert before.returncode == 2 and f"'{NAME}' is not a valid value" in before.stderr


def test_c_the_tables_list_its_run(copy, tmp_path):
    """The results tree of tests/eval_fake_results.py plus a refcams run on room, n = 3: what
    its command wrote (run on a small synthetic scene) and a Bridge-mode folder (uniform)."""
    from camio.synthetic import write_synthetic_scene

    results, _ = build(tmp_path)
    scene = write_synthetic_scene(tmp_path / "scene", views=6, width=32, n_gt_points=200, n_ref_points=50)
    names = sorted(p.name for p in (scene / "images").iterdir())[:3]
    (tmp_path / "train.txt").write_text("\n".join(names) + "\n")
    run = results / "mip360" / "room" / "n3" / NAME
    proc = subprocess.run([sys.executable, "-m", f"evaluation.initialisers.{NAME}", "--scene", str(scene),
                           "--image-list", str(tmp_path / "train.txt"), "--out", str(run)],
                          cwd=copy, env=_env(copy), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((run / "status.json").read_text())["registered"] == 3 and (run / "sparse" / "0").is_dir()
    _mode_run(run / "uniform", "room", 3, NAME, "uniform")

    out = tmp_path / "tables"
    proc = subprocess.run([sys.executable, "-m", "evaluation", "tables", "--results", str(results), "--out", str(out)],
                          cwd=copy, env=_env(copy), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    runs = pd.read_parquet(out / "runs.parquet")
    ours = runs[runs["init"] == NAME]
    assert len(ours) == 1 and ours.iloc[0]["bridge_mode"] == "uniform" and bool(ours.iloc[0]["success_paper"])
    assert ours.iloc[0]["psnr"] == pytest.approx(psnr_of("room", 3, NAME, "uniform"))
    assert NAME in (out / "tables.md").read_text()
