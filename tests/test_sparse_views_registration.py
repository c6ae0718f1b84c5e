"""A pre-registered evaluation proves from git that it was registered before its runs.

``python -m experiments.sparse_views.seeds report`` and ``python -m experiments.sparse_views
summary`` write a ``registration`` block (the commit that added the registration, or gave each
evaluation scene its role, against each run's time) and one sentence of it on their page
(experiments/sparse_views/provenance.py). Every test builds its own small git repository in
``tmp_path`` with fixed commit times, so nothing depends on this repository's history.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import yaml

from tests._cli import ENV, ROOT, run

REG = {"name": "t", "role": "evaluation", "scenes": ["a", "b"], "n": 3, "seeds": [0], "iterations": 10,
       "variants": {"paper": {"recipe": "paper"}, "paper-mvs": {"recipe": "paper", "init": "mvs", "bridge_mode": "gated"}},
       "targets": [{"better": "paper-mvs", "than": "paper", "by": 1.0}]}
DAY = "2030-01-01"
REGISTERED_AT = f"{DAY}T10:00:00+00:00"


def _git(repo, *args, at: str | None = None) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@example.org", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@example.org", "GIT_CONFIG_NOSYSTEM": "1", "GIT_CONFIG_GLOBAL": os.devnull}
    if at:
        env |= {"GIT_AUTHOR_DATE": at, "GIT_COMMITTER_DATE": at}
    return subprocess.run(["git", "-C", str(repo), *args], env=env, check=True, capture_output=True,
                          text=True).stdout.strip()


def _commit(repo, at: str, message: str) -> str:
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "--no-gpg-sign", "-m", message, at=at)
    return _git(repo, "rev-parse", "HEAD")


def _record(repo, scene, variant, **stamp):
    """A seed-comparison run record of ``scene`` and ``variant`` with the time stamps ``stamp``
    (``started_at``, ``recorded``: the runner's; none at all: an older record)."""
    p = repo / "records" / "runs" / f"{scene}_n3_{variant}_s0_i10.json"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps({"psnr": 15.0 + (variant == "paper-mvs"), "ssim": 0.5, "lpips_alex": 0.4,
                             "lpips_vgg": 0.5, "gaussians": 10, "seed_gaussians": 5,
                             "curve": {"coverage": [0.9], "psnr_covered": [16.0]}, **stamp}))
    return p.stem


def _report(tmp_path, repo, registration, **env):
    doc = tmp_path / "doc.md"
    proc = subprocess.run([sys.executable, "-m", "experiments.sparse_views.seeds", "report", "--registration",
                           str(registration), "--records", str(repo / "records"), "--doc", str(doc)],
                          capture_output=True, text=True, cwd=ROOT, env={**ENV, **env}, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads((repo / "records" / "t.json").read_text())["registration"], doc.read_text()


def _init(tmp_path, name="repo"):
    repo = tmp_path / name
    repo.mkdir()
    _git(repo, "init", "-q")
    return repo


def test_a_registration_committed_before_its_runs_is_shown_so(tmp_path):
    """Registration first (then moved: the commit that added it still counts), runs later: every
    run is after it, the JSON holds the commit and its time, the page says so without either."""
    repo = _init(tmp_path)
    (repo / "reg.yaml").write_text(yaml.safe_dump(REG))
    added = _commit(repo, REGISTERED_AT, "register")
    runs = [_record(repo, s, v, started_at=f"{DAY}T11:00:00+00:00", recorded=DAY)
            for s in ("a", "b") for v in ("paper", "paper-mvs")]
    _commit(repo, f"{DAY}T12:00:00+00:00", "runs")
    (repo / "registered").mkdir()
    _git(repo, "mv", "reg.yaml", "registered/reg.yaml")
    _commit(repo, f"{DAY}T13:00:00+00:00", "move")
    block, page = _report(tmp_path, repo, repo / "registered" / "reg.yaml")
    assert block["commit"] == added and block["committed_at"] == REGISTERED_AT
    assert block["runs"] == len(runs) == block["runs_after"] == 4
    assert block["runs_before"] == block["runs_unplaced"] == [] and block["pre_registered"] is True
    assert "Registered in the commit that added" in page and "before all 4 of its runs" in page
    assert added[:7] not in page and "2030-" not in page  # no hash or date in prose


def test_runs_made_before_the_registration_are_named_and_the_figure_is_not_pre_registered(tmp_path):
    """The reverse order: records committed before the registration. A record with a day before
    it, or none at all but a commit before it, is *before*; a record of the registration's day
    committed after it cannot be placed; one with its start time after it is *after*."""
    repo = _init(tmp_path)
    early = _record(repo, "a", "paper", recorded="2029-12-31")           # the day before
    unstamped = _record(repo, "a", "paper-mvs")                           # no stamp: its commit time
    _commit(repo, f"{DAY}T09:00:00+00:00", "runs first")
    (repo / "reg.yaml").write_text(yaml.safe_dump(REG))
    _commit(repo, REGISTERED_AT, "register")
    same_day = _record(repo, "b", "paper", recorded=DAY)                  # committed after, same day
    later = _record(repo, "b", "paper-mvs", started_at=f"{DAY}T10:30:00+00:00")
    _commit(repo, f"{DAY}T11:00:00+00:00", "runs after")
    block, page = _report(tmp_path, repo, repo / "reg.yaml")
    assert block["runs_before"] == sorted([early, unstamped]) and block["runs_unplaced"] == [same_day]
    assert block["runs_after"] == 1 and block["pre_registered"] is False, later
    assert "Not pre-registered: 2 of the 4 runs were made before the commit that added" in page
    assert f"`{early}`" in page and f"`{unstamped}`" in page and "1 more cannot be placed" in page


def test_without_history_the_report_says_not_verifiable_and_still_writes(tmp_path):
    """A tarball (no git checkout) and a shallow clone: the check is named as not verifiable, the
    figures are written, the command succeeds."""
    repo = _init(tmp_path)
    (repo / "reg.yaml").write_text(yaml.safe_dump(REG))
    _commit(repo, REGISTERED_AT, "register")
    for s in ("a", "b"):
        for v in ("paper", "paper-mvs"):
            _record(repo, s, v, recorded=DAY)
    _commit(repo, f"{DAY}T11:00:00+00:00", "runs")
    (repo / "late.txt").write_text("x")
    _commit(repo, f"{DAY}T12:00:00+00:00", "later")
    tarball = tmp_path / "tarball"
    shutil.copytree(repo, tarball, ignore=shutil.ignore_patterns(".git"))
    # never the git repository around tmp_path, if there is one
    block, page = _report(tmp_path, tarball, tarball / "reg.yaml", GIT_CEILING_DIRECTORIES=str(tmp_path))
    assert block["verifiable"] is False and block["reason"].startswith("registration not verifiable here")
    assert block["runs"] == 4 and block["pre_registered"] is None
    assert "Registration not verifiable here" in page
    shallow = tmp_path / "shallow"
    _git(tmp_path, "clone", "-q", "--depth", "1", f"file://{repo}", str(shallow))
    block, page = _report(tmp_path, shallow, shallow / "reg.yaml")
    assert block["verifiable"] is False and "shallow" in block["reason"]


def _scenes(role):
    return {"version": 1, "split": {"rule": "every8"},
            "scenes": [{"name": "t", "role": "tuning", "kind": "object", "views": [3], "local": "data/t"},
                       {"name": "a", "role": role, "kind": "object", "views": [3], "local": "data/a"}]}


def _grid_record(repo, scene, recipe, seed, **stamp):
    p = repo / "rec" / "runs" / f"{scene}_n3_{recipe}_s{seed}_i10.json"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps({"scene": scene, "role": "evaluation", "n": 3, "recipe": recipe, "seed": seed,
                             "iterations": 10, "psnr": 18.0 + seed, "ssim": 0.5, "lpips_alex": 0.3,
                             "lpips_vgg": 0.35, "gaussians": 100, "train_s": 1.0, "backend": "cpu", **stamp}))
    return p.stem


def test_the_grid_summary_checks_each_evaluation_scene_from_the_commit_that_gave_it_its_role(tmp_path):
    """scenes.yaml lists scene ``a`` as reserve, then a later commit makes it an evaluation scene:
    that commit is its registration (not a still later edit of the file); a run before it is
    named, runs after it count."""
    repo = _init(tmp_path)
    (repo / "scenes.yaml").write_text(yaml.safe_dump(_scenes("reserve"), sort_keys=False))
    _commit(repo, f"{DAY}T08:00:00+00:00", "reserve")
    early = _grid_record(repo, "a", "paper", 0, started_at=f"{DAY}T09:00:00+00:00")
    _grid_record(repo, "t", "paper", 0, started_at=f"{DAY}T09:00:00+00:00")  # a tuning scene: not checked
    (repo / "scenes.yaml").write_text(yaml.safe_dump(_scenes("evaluation"), sort_keys=False))
    made = _commit(repo, REGISTERED_AT, "a becomes an evaluation scene")
    after = [_grid_record(repo, "a", rc, 1, started_at=f"{DAY}T11:00:00+00:00") for rc in ("paper", "sparse")]
    _commit(repo, f"{DAY}T12:00:00+00:00", "runs")
    # a later change of the file that leaves the scene's role as it was is no registration
    later = _scenes("evaluation")
    later["scenes"].append({"name": "b", "role": "reserve", "kind": "object", "views": [3], "local": "data/b"})
    (repo / "scenes.yaml").write_text(yaml.safe_dump(later, sort_keys=False))
    _commit(repo, f"{DAY}T13:00:00+00:00", "a reserve scene")
    doc = tmp_path / "grid.md"
    proc = run(["-m", "experiments.sparse_views", "--protocol", str(repo / "scenes.yaml"), "--records",
                str(repo / "rec"), "summary", "--doc", str(doc)])
    assert proc.returncode == 0, proc.stderr
    block = json.loads((repo / "rec" / "summary.json").read_text())["registration"]
    assert block["commit"] == made and block["committed_at"] == REGISTERED_AT and list(block["scenes"]) == ["a"]
    assert block["runs"] == 3 and block["runs_after"] == len(after) == 2 and block["runs_before"] == [early]
    assert block["pre_registered"] is False and block["scenes"]["a"]["commit"] == made
    page = doc.read_text()
    assert "Not pre-registered: 1 of the 3 runs was made before the commits that gave each evaluation scene" in page
    assert f"`{early}`" in page and made[:7] not in page
    # without the early run every run on the evaluation scene follows its registration
    (repo / "rec" / "runs" / f"{early}.json").unlink()
    proc = run(["-m", "experiments.sparse_views", "--protocol", str(repo / "scenes.yaml"), "--records",
                str(repo / "rec"), "summary", "--doc", str(doc)])
    assert proc.returncode == 0, proc.stderr
    assert json.loads((repo / "rec" / "summary.json").read_text())["registration"]["pre_registered"] is True
    assert "before all 2 of their runs" in doc.read_text()
