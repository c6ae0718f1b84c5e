"""Adding an initialiser, a dataset format or a training recipe touches only the files
docs/contracts.md names for it ("Adding an initialiser", "Adding a dataset format", "Adding a
recipe").

A copy of the project's tracked files gets:

* one initialiser more, ``refcams`` (the reference cameras and at most ``max_points`` points of
  the training views: a COLMAP model and status.json, the contract of the workflow's common
  rule), WITH an option (``max_points``, default 100) and a label, by its entry in
  evaluation/initialisers/registry.py and its module evaluation/initialisers/refcams.py;
* one dataset format more, ``camlist`` (``cameras.lst``: per image a line ``NAME K R t``, the
  projection of a Middlebury ``*_par.txt`` without its count line), by its reader and entry in
  camio/datasets.py and its row in docs/contracts.md;
* one training recipe more, ``longdrop`` (DropGaussian with one value changed: the final dropout
  rate 0.3), a preset stating that difference in splat_train/recipes.py and its row in
  docs/reference.md.

The test checks that nothing else differs, and that those lists are what docs/contracts.md
says. Then, in the copy, through the commands a user runs:

(a) ``python -m camio convert --help`` offers the format, and converts (auto-detects) a scene in it;
(b) the config check accepts ``initialisers: [refcams]``, its option block and ``format:
    camlist``, and suggests the names for a typo, where the project's own check refuses them;
(c) the workflow plans their jobs (a dry run): the common rule runs the command with the
    option's flag (the config's value, else the entry's default), the Bridge seeds from its
    model in uniform mode, and the scene in the new format is converted with ``--format camlist``;
(d) the evaluation tables list its run, by its label, after the registry's other initialisers,
    and the report shows it by its label, read from a small results tree in which the run
    folder is what its command wrote.
"""

from __future__ import annotations

import json
import os
import re
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
LABEL = "reference cameras"
FORMAT = "camlist"

# The registry entry: a CPU command writing a COLMAP model and status.json, needing reference
# cameras, with one option.
ENTRY = (f'    Initialiser("{NAME}", "evaluation.initialisers.{NAME}", _MODEL, "status.json", False,\n'
         f'                frozenset({{"reference"}}), label="{LABEL}",\n'
         '                options=(Option("max_points", "integer", 100, "keep at most this many points", minimum=1),)),\n')
# Its module: python -m evaluation.initialisers.refcams --scene S --image-list L --out D [--max-points N].
MODULE = '''"""The reference cameras and points of the training views, as an initialiser.

    python -m evaluation.initialisers.refcams --scene SCENE --image-list TRAIN_TXT --out DIR [--max-points N]

Writes DIR/sparse/0 (COLMAP text) and DIR/status.json.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from runtime.atomic import write_json
from camio.colmap import read_model, write_text_model
from runtime.checks import flag
from runtime.outdir import prepare_out, run_stage
from evaluation.initialisers.views import read_image_list

log = logging.getLogger(__name__)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.refcams")
    p.add_argument("--scene", required=True)
    p.add_argument("--image-list", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--max-points", type=flag(int, 1), required=True)
    args = p.parse_args(argv)

    def work() -> int:
        names = read_image_list(args.image_list)
        ref = read_model(Path(args.scene) / "sparse" / "0")
        cams = [c for c in ref.cameras if c.name in set(names)]
        out = prepare_out(args.out, {"--scene": args.scene, "--image-list": args.image_list},
                          "evaluation.refcams")
        keep = slice(0, args.max_points)
        write_text_model(out / "sparse" / "0", cams, ref.points[keep], ref.colors[keep])
        write_json(out / "status.json", {
            "success_paper": len(cams) == len(names), "aligned_ok": len(cams) >= 3, "registered": len(cams),
            "n_images": len(names), "points": len(ref.points[keep]), "reason": None, "wall_time_s": 0.0})
        return 0

    return run_stage(log, work)


if __name__ == "__main__":
    sys.exit(main())
'''
# The format's reader (camio/datasets.py) and its entry in DATASET_FORMATS.
READER = f'''def read_{FORMAT}(root: Path, image_dir: Path, names: list[str]) -> SparseModel:
    """Cameras of ``root/cameras.lst``: per image ``NAME k11 .. k33 r11 .. r33 t1 t2 t3``."""
    table = read_middlebury_par(root / "cameras.lst")
    return SparseModel([Camera(n, *image_size(image_dir / n), *table[n]) for n in names])


'''
FORMAT_ENTRY = (f'    DatasetFormat("{FORMAT}", "one line per image: its name, K, R and t", "cameras.lst", True,\n'
                f'                  lambda r: (r / "cameras.lst").is_file(), read_{FORMAT}),\n')
FORMAT_ROW = f"| `{FORMAT}` | one line per image: its name, K, R and t | `cameras.lst` | yes |\n"
# The recipe: a preset of one changed value, its place in RECIPES and its help line, and its row
# in docs/reference.md section 3a.
RECIPE = "longdrop"
PRESET = (f'{RECIPE.upper()} = replace(DROPGAUSSIAN, recipe="{RECIPE}", parts=(DropoutConfig(rate=0.3),))\n\n')
RECIPE_SUMMARY = f'    "{RECIPE}": "DropGaussian with a final dropout rate of 0.3",\n'
RECIPE_ROW = f"| `{RECIPE}` | `dropgaussian` with the final dropout rate 0.3 |\n"


def _tracked() -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, text=True, check=True)
    return [p for p in out.stdout.split("\0") if p and (REPO / p).is_file()]


def _edit(path: Path, anchor: str, insert: str, before: bool = True) -> None:
    text = path.read_text()
    assert text.count(anchor) == 1, f"{path.name}: the anchor {anchor!r} moved; update the test"
    path.write_text(text.replace(anchor, insert + anchor if before else anchor + insert))


@pytest.fixture(scope="module")
def copy(tmp_path_factory) -> Path:
    """The project's tracked files, with ``refcams`` and ``camlist`` added."""
    root = tmp_path_factory.mktemp("added") / "repo"
    for rel in _tracked():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, root / rel)
    init = root / "evaluation" / "initialisers"
    _edit(init / "registry.py", "\n)}\nNAMES = tuple(INITIALISERS)", "\n" + ENTRY.rstrip("\n"))
    (init / f"{NAME}.py").write_text(MODULE)
    datasets = root / "camio" / "datasets.py"
    _edit(datasets, "# ------------------------------------------------------------------------------- the registry",
          READER)
    _edit(datasets, '    DatasetFormat("folder",', FORMAT_ENTRY)
    _edit(root / "docs" / "contracts.md", "| `folder` |", FORMAT_ROW)
    recipes = root / "splat_train" / "recipes.py"
    _edit(recipes, "RECIPES: dict[str, ConfigTree] = ", PRESET)
    _edit(recipes, '"mcmc": MCMC', f', "{RECIPE}": {RECIPE.upper()}', before=False)
    _edit(recipes, "}\n\n\ndef recipe_config", RECIPE_SUMMARY)
    _edit(root / "docs" / "reference.md", "| `mcmc` | 3DGS as MCMC", RECIPE_ROW)
    return root


def _env(root: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(root), "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}


def _run(root: Path, args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=root, env=_env(root), capture_output=True, text=True,
                          timeout=timeout)


def _documented(section: str, name: str) -> set[str]:
    """The files a section of docs/contracts.md lists ("1. `path`: ..."), ``<name>`` filled in."""
    text = (REPO / "docs" / "contracts.md").read_text()
    body = text.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    return {m.replace("<name>", name) for m in re.findall(r"^\d+\. `([^`]+)`", body, flags=re.MULTILINE)}


def test_the_copy_differs_by_the_documented_files_only(copy):
    differ = {rel for rel in _tracked() if (copy / rel).read_bytes() != (REPO / rel).read_bytes()}
    added = {str(p.relative_to(copy)) for p in copy.rglob("*")
             if p.is_file() and "__pycache__" not in p.parts} - set(_tracked())
    documented = (_documented("Adding an initialiser", NAME) | _documented("Adding a dataset format", FORMAT)
                  | _documented("Adding a recipe", RECIPE))
    assert documented == {"evaluation/initialisers/registry.py", f"evaluation/initialisers/{NAME}.py",
                          "camio/datasets.py", "docs/contracts.md", "splat_train/recipes.py", "docs/reference.md"}
    assert differ | added == documented, (differ, added)
    code = (f"from evaluation.initialisers import registry as r; i = r.get('{NAME}'); "
            "print(r.with_common_rule(), i.needs, [o.flag for o in i.options])")
    out = _run(copy, ["-c", code])
    assert out.stdout.strip() == f"('{NAME}',) frozenset({{'reference'}}) ['--max-points']", out.stderr


def _camlist_scene(tmp_path: Path) -> Path:
    """A synthetic scene rewritten as images/ + cameras.lst (no COLMAP model)."""
    from camio.colmap import read_model
    from camio.synthetic import write_synthetic_scene

    synth = write_synthetic_scene(tmp_path / "synth", views=8, width=32, n_gt_points=100, n_ref_points=20)
    scene = tmp_path / "camlist_scene"
    shutil.copytree(synth / "images", scene / "images")
    lines = [" ".join([c.name, *(f"{v:.12g}" for v in (*c.K.ravel(), *c.cam_from_world[:, :3].ravel(),
                                                        *c.cam_from_world[:, 3]))])
             for c in read_model(synth / "sparse" / "0").cameras]
    (scene / "cameras.lst").write_text("\n".join(lines) + "\n")
    return scene


def test_a_convert_offers_and_reads_the_format(copy, tmp_path):
    text = " ".join(_run(copy, ["-m", "camio", "convert", "--help"]).stdout.split())
    assert f",middlebury,{FORMAT},folder}}" in text and f"{FORMAT}: one line per image: its name, K, R and t" in text
    assert FORMAT not in _run(REPO, ["-m", "camio", "convert", "--help"]).stdout  # the project's own
    scene = _camlist_scene(tmp_path)
    proc = _run(copy, ["-m", "camio", "convert", "--src", str(scene), "--out", str(tmp_path / "out"), "--n", "3"])
    assert proc.returncode == 0, proc.stderr
    info = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert info["format"] == FORMAT and info["n_reference_cameras"] == 8  # detected, cameras read


def _check(root: Path, cfg: dict, tmp_path: Path) -> subprocess.CompletedProcess:
    f = tmp_path / "config.yaml"
    f.write_text(yaml.safe_dump(cfg))
    return _run(root, ["workflow/scripts/check_config.py", str(f)], timeout=60)


def test_b_the_config_check_reads_both_registries(copy, tmp_path):
    base = yaml.safe_load((REPO / "config.yaml").read_text())
    scenes = {"datasets": {"mine": {"scenes": {"a": {"path": "a", "format": FORMAT}}}}}
    ok = _check(copy, {**base, **scenes, "initialisers": ["colmap", NAME], NAME: {"max_points": 7}}, tmp_path)
    assert ok.returncode == 0, ok.stderr
    typo = _check(copy, {**base, "initialisers": ["refcam"]}, tmp_path)
    assert typo.returncode == 2 and f"'refcam' is not a valid value; did you mean '{NAME}'?" in typo.stderr
    key = _check(copy, {**base, "initialisers": [NAME], NAME: {"max_point": 7}}, tmp_path)
    assert key.returncode == 2 and f"unknown key '{NAME}.max_point'; did you mean 'max_points'?" in key.stderr
    low = _check(copy, {**base, "initialisers": [NAME], NAME: {"max_points": 0}}, tmp_path)
    assert low.returncode == 2 and f"{NAME}.max_points: 0 is less than the minimum of 1" in low.stderr
    fmt = _check(copy, {**base, "datasets": {"mine": {"scenes": {"a": {"path": "a", "format": "camlst"}}}}}, tmp_path)
    assert fmt.returncode == 2 and f"did you mean '{FORMAT}'?" in fmt.stderr
    before = _check(REPO, {**base, **scenes, "initialisers": [NAME]}, tmp_path)  # the project without them
    assert before.returncode == 2 and f"initialisers.0: '{NAME}' is not a valid value" in before.stderr
    assert f"'{FORMAT}' is not a valid value" in before.stderr


def _dry_run(root: Path, tmp_path: Path, extra: dict) -> subprocess.CompletedProcess:
    scene = _camlist_scene(tmp_path)
    cfg = {"results": "results", "views": [3, 6], "initialisers": ["colmap", NAME], "train": {"iterations": 10},
           "datasets": {"synthetic": {"scenes": {"bundled": {"synth": {"views": 24, "width": 64}}}},
                        "mine": {"scenes": {"lst": {"path": str(scene), "format": FORMAT, "views": [3],
                                                    "initialisers": [NAME]}}}},
           **extra}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    return subprocess.run([SNAKEMAKE, "-n", "-p", "--snakefile", str(root / "Snakefile"), "--directory",
                           str(tmp_path), "--configfile", str(tmp_path / "config.yaml")],
                          env=_env(root), capture_output=True, text=True, timeout=180)


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_c_the_workflow_plans_their_jobs(copy, tmp_path):
    proc = _dry_run(copy, tmp_path, {NAME: {"max_points": 7}})
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    blocks = out.split("\n\n")
    init_jobs = [b for b in blocks if "rule registry_init:" in b]
    assert len(init_jobs) == 3 and all(f"init={NAME}" in b for b in init_jobs), init_jobs
    for n in (3, 6):
        assert (f"python -m evaluation.initialisers.{NAME} --scene results/synthetic/bundled/synth "
                f"--image-list results/synthetic/bundled/n{n}/train.txt --out results/synthetic/bundled/n{n}/{NAME} "
                "--max-points 7 ") in out
    for rule in ("bridge_colmap", "train_splats", "pose_eval", "image_metrics"):
        assert any(f"rule {rule}:" in b and f"init={NAME}" in b for b in blocks), rule
    assert f"n3/{NAME}/uniform/bridge/seed.ply" in out and f"n3/{NAME}/gated" not in out
    # the scene in the new format: converted with its format, then planned as a scene with cameras
    assert f"--format {FORMAT}" in out and "results/mine/lst/n3/refcams/pose.json" in out
    default = _dry_run(copy, tmp_path / "default", {})  # the option left out: the entry's default
    assert default.returncode == 0 and f"--out results/synthetic/bundled/n3/{NAME} --max-points 100 " in default.stdout


def test_d_the_tables_list_its_run_by_its_label(copy, tmp_path):
    """The results tree of tests/eval_fake_results.py plus a refcams run on room, n = 3: what
    its command wrote (run on a small synthetic scene) and a Bridge-mode folder (uniform)."""
    from camio.synthetic import write_synthetic_scene

    results, _ = build(tmp_path)
    scene = write_synthetic_scene(tmp_path / "scene", views=6, width=32, n_gt_points=200, n_ref_points=50)
    names = sorted(p.name for p in (scene / "images").iterdir())[:3]
    (tmp_path / "train.txt").write_text("\n".join(names) + "\n")
    run = results / "mip360" / "room" / "n3" / NAME
    proc = _run(copy, ["-m", f"evaluation.initialisers.{NAME}", "--scene", str(scene), "--image-list",
                       str(tmp_path / "train.txt"), "--out", str(run), "--max-points", "20"], timeout=60)
    assert proc.returncode == 0, proc.stderr
    status = json.loads((run / "status.json").read_text())
    assert status["registered"] == 3 and status["points"] == 20 and (run / "sparse" / "0").is_dir()
    _mode_run(run / "uniform", "room", 3, NAME, "uniform")

    out = tmp_path / "tables"
    proc = _run(copy, ["-m", "evaluation", "tables", "--results", str(results), "--out", str(out)])
    assert proc.returncode == 0, proc.stderr
    runs = pd.read_parquet(out / "runs.parquet")
    ours = runs[runs["init"] == NAME]
    assert len(ours) == 1 and ours.iloc[0]["bridge_mode"] == "uniform" and bool(ours.iloc[0]["success_paper"])
    assert ours.iloc[0]["psnr"] == pytest.approx(psnr_of("room", 3, NAME, "uniform"))
    table_two = (out / "tables.md").read_text().split("## Table II", 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in table_two.splitlines() if ln.startswith("| mip360 ")]
    inits = [ln.split("|")[2].strip() for ln in rows]
    assert LABEL in inits and NAME not in inits and inits.index(LABEL) > max(
        i for i, x in enumerate(inits) if x == "colmap"), inits
    report = tmp_path / "report"
    proc = _run(copy, ["-m", "evaluation", "report", "--results", str(results), "--out", str(report)], timeout=180)
    assert proc.returncode == 0, proc.stderr
    assert f"{LABEL} (uniform)" in (report / "index.html").read_text()  # its render-grid column, by its label


@pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")
def test_e_the_recipe_reaches_the_help_the_check_and_the_training_jobs(copy, tmp_path):
    helptext = " ".join(_run(copy, ["-m", "splat_train", "--help"]).stdout.split())
    assert f"'{RECIPE}': DropGaussian with a final dropout rate of 0.3" in helptext and f",mcmc,{RECIPE}}}" in helptext
    assert RECIPE not in _run(REPO, ["-m", "splat_train", "--help"]).stdout  # the project's own
    base = yaml.safe_load((REPO / "config.yaml").read_text())
    cfg = {**base, "train": {**base.get("train", {}), "recipe": RECIPE}}
    assert _check(copy, cfg, tmp_path).returncode == 0
    before = _check(REPO, cfg, tmp_path)
    assert before.returncode == 2 and f"'{RECIPE}' is not a valid value" in before.stderr
    proc = _dry_run(copy, tmp_path, {"train": {"iterations": 10, "recipe": RECIPE}})
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    train_jobs = [b for b in out.split("\n\n") if "rule train_splats:" in b]
    assert train_jobs and all(f"--recipe {RECIPE}" in b for b in train_jobs), train_jobs[:1]
    # the preset states its one difference: every flat key but the dropout rate is dropgaussian's
    code = ("from splat_train.recipes import recipe_defaults as d; a, b = d('dropgaussian'), d('" + RECIPE + "'); "
            "print(sorted(k for k in a if a[k] != b[k]), b['dropout_rate'])")
    res = _run(copy, ["-c", code])
    assert res.stdout.strip() == "['dropout_rate'] 0.3", res.stderr
