"""experiments/sparse_views: the protocol file, and the table rebuilt from run records.

The records here are made up to exercise the aggregation (means, paired differences, the
targets' verdicts); the benchmark's real records are in experiments/records/sparse_views.
"""

import json
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from benchmarks.backend_agree import backend_agree
from experiments.sparse_views import protocol
from experiments.sparse_views.runs import RECORD_KEYS
from experiments.sparse_views.summary import spread, write_summary

REPO = Path(__file__).resolve().parents[1]


def test_shipped_protocol_keeps_tuning_and_evaluation_apart():
    scenes = protocol.load()
    roles = {s.name: s.role for s in scenes}
    assert roles["llff__fern"] == "tuning" and roles["synthetic"] == "tuning"
    ev = [s for s in scenes if s.role == "evaluation"]
    assert len({s.name for s in scenes}) == len(scenes)
    # the benchmark's own bar: at least four evaluation scenes, of at least two kinds
    assert len(ev) >= 4 and len({s.kind for s in ev}) >= 2, [(s.name, s.kind) for s in ev]
    for s in ev:  # every evaluation scene names where it comes from
        assert s.source, s.name


def test_reserve_scenes_are_listed_but_never_run():
    """Scenes held back for the evaluation after the next change of values (none between the
    change that makes them the evaluation and the next scenes found): public like the evaluation
    scenes, with no run record, and ``run`` refuses their role."""
    reserve = [s for s in protocol.load() if s.role == "reserve"]
    assert all(s.kind and s.source.get("repo") and s.source.get("licence") for s in reserve)
    runs = REPO / "experiments" / "records" / "sparse_views" / "runs"
    assert not [p.name for s in reserve for p in runs.glob(f"{s.name}_n*.json")]
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "run", "--role", "reserve", "--work", "w"],
                         cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 2 and "invalid choice: 'reserve'" in out.stderr


def test_protocol_resolves_data_folders(tmp_path, monkeypatch):
    """--data DIR (or $SPARSE_VIEWS_DATA) puts every real scene at DIR/<name>, as fetch_scenes.py
    leaves them; a generated scene has no folder and is always available."""
    monkeypatch.delenv(protocol.DATA_ENV, raising=False)
    scenes = {s.name: s for s in protocol.load(data=tmp_path)}
    assert scenes["ingp__fox"].path == tmp_path / "ingp__fox" and not scenes["ingp__fox"].available
    assert scenes["synthetic"].path is None and scenes["synthetic"].available
    monkeypatch.setenv(protocol.DATA_ENV, str(tmp_path / "x"))
    assert {s.name: s for s in protocol.load()}["ingp__fox"].path == tmp_path / "x" / "ingp__fox"


def _rec(scene, role, recipe, seed, psnr, lpips, best=None, gaussians=1000):
    return {"scene": scene, "role": role, "n": 3, "recipe": recipe, "seed": seed, "iterations": 1000,
            "psnr": psnr, "ssim": 0.5, "lpips_alex": lpips, "lpips_vgg": lpips + 0.05, "gaussians": gaussians,
            "train_s": 10.0, "backend": "cpu-kernel", "best_psnr": best if best is not None else psnr}


def test_summary_cli_rebuilds_table_and_verdicts(tmp_path):
    runs = tmp_path / "rec" / "runs"
    runs.mkdir(parents=True)
    recs = []
    for scene in ("a", "b"):
        for seed in (0, 1, 2):
            recs.append(_rec(scene, "evaluation", "paper", seed, 18.0 + 0.1 * seed, 0.30, best=19.0 + 0.1 * seed))
            recs.append(_rec(scene, "evaluation", "sparse", seed, 19.0 + 0.1 * seed, 0.28 + 0.01 * seed,
                             gaussians=70_000 if scene == "b" else 5_000))
        recs.append(_rec("t", "tuning", "sparse", 0, 25.0, 0.1))
    recs.append(_rec("c", "evaluation", "paper", 0, 30.0, 0.1))  # a scene the grid has not finished
    # an earlier version kept beside the recipes, on one scene: in the table, not in the targets
    recs.append(_rec("a", "evaluation", "mcmc-r13", 0, 25.0, 0.1))
    # n = 6 runs count in their own measures, never in the n = 3 targets
    recs += [dict(_rec("a", "evaluation", rc, 0, p, 0.2, gaussians=g), n=6)
             for rc, p, g in (("paper", 21.0, 9_000), ("sparse", 20.0, 99_000))]
    # a shorter grid at n = 3: its own measures; the targets take the most iterations run
    recs += [dict(_rec("a", "evaluation", rc, 0, p, 0.2, gaussians=g), iterations=300)
             for rc, p, g in (("paper", 10.0, 500), ("sparse", 12.0, 88_000))]
    for i, r in enumerate(recs):
        (runs / f"{i}.json").write_text(json.dumps(r))
    doc = tmp_path / "results.md"
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--records", str(tmp_path / "rec"),
                          "summary", "--doc", str(doc)], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    s = json.loads((tmp_path / "rec" / "summary.json").read_text())
    assert len(s["rows"]) == len(recs) and set(RECORD_KEYS) <= set(s["rows"][0])
    t = s["targets"]
    assert t["evaluation_scenes"] == ["a", "b"] and t["incomplete_scenes"] == ["c"]
    assert t["mean_final_psnr"]["sparse"] == pytest.approx(19.1) and t["mean_final_psnr"]["paper"] == pytest.approx(18.1)
    assert t["psnr_lead_over_best_other"] == pytest.approx(1.0) and t["psnr_lead_ok"]
    # LPIPS sparse - paper: -0.02, -0.01, 0.00 on both scenes: not above zero
    assert t["lpips_alex_minus_paper"]["mean"] == pytest.approx(-0.01) and t["lpips_alex_no_worse"]
    # sparse's final (19.x) equals paper's best (19.x) on both scenes
    assert t["final_ge_paper_best_scenes"] == 2
    assert t["max_gaussians_ours"] == 70_000 and not t["gaussians_ok"]
    assert t["iterations"] == 1000 and s["measures_by_n"]["n3_i1000"] == t
    short = s["measures_by_n"]["n3_i300"]
    assert short["psnr_lead_over_best_other"] == pytest.approx(2.0) and short["max_gaussians_ours"] == 88_000
    six = s["measures_by_n"]["n6_i1000"]
    assert six["evaluation_scenes"] == ["a"] and six["psnr_lead_over_best_other"] == pytest.approx(-1.0)
    assert six["max_gaussians_ours"] == 99_000
    text = doc.read_text()
    assert "| a | " in text and " | mcmc-r13 | 1 | 25.00" in text
    assert "## The same measures at n = 6, 1000 iterations" in text
    assert "## Evaluation scenes" in text and "## Tuning scenes" in text and "not met" in text
    assert "highest mean PSNR of the recipes: 2 of 2" in text and t["spread"]["sparse_best_scenes"] == ["a", "b"]
    assert "the lead with one scene left out: +1.00 dB" in text


def test_users_own_evaluation_scene_needs_no_public_source(tmp_path):
    """A scenes file for one's own captures: name, role, kind, views and where the data is;
    ``source`` and ``licence`` belong to scenes fetched from public repositories."""
    f = tmp_path / "mine.yaml"
    f.write_text("scenes:\n- {name: desk, role: evaluation, kind: forward-facing, views: [3],\n"
                 "   local: /nonexistent/desk, convert: [--format, llff]}\n")
    (scene,) = protocol.load(f)
    assert scene.role == "evaluation" and scene.convert == ("--format", "llff") and not scene.available
    assert protocol.load(f, data=tmp_path)[0].path == tmp_path / "desk"
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--protocol", str(f), "--records",
                          str(tmp_path / "rec"), "run", "--role", "evaluation", "--work", str(tmp_path / "w")],
                         cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0 and "SKIP desk" in out.stdout, out.stdout + out.stderr
    f.write_text(f.read_text().replace("kind: forward-facing, ", ""))  # the tables group by kind
    with pytest.raises(ValueError, match="'kind' missing"):
        protocol.load(f)


def test_spread_of_the_lead_by_kind_best_scene_and_leave_one_out():
    psnr = {"sparse": {"a": 20.0, "b": 10.0, "c": 15.0}, "mcmc": {"a": 19.0, "b": 12.0, "c": 14.0},
            "paper": {"a": 18.0, "b": 11.0, "c": 14.5}}
    per = {rc: {sc: {"psnr": {"mean": v}} for sc, v in d.items()} for rc, d in psnr.items()}
    sp = spread(per, ["a", "b", "c"], {"a": "forward-facing", "b": "object-centric", "c": "forward-facing"})
    ff = sp["by_kind"]["forward-facing"]
    assert ff["scenes"] == ["a", "c"] and ff["mean_final_psnr"]["sparse"] == pytest.approx(17.5)
    assert ff["psnr_lead_over_best_other"] == pytest.approx(17.5 - 16.5)  # mcmc 16.5, paper 16.25
    assert sp["by_kind"]["object-centric"]["psnr_lead_over_best_other"] == pytest.approx(-2.0)
    assert sp["sparse_best_scenes"] == ["a", "c"]
    # leads without a: 12.5 - 13.0 = -0.5; without b: 17.5 - 16.5 = +1.0; without c: 15 - 15.5 = -0.5
    lo = sp["lead_leave_one_out"]
    assert lo["max"] == pytest.approx(1.0) and lo["max_without"] == "b"
    assert lo["min"] == pytest.approx(-0.5) and lo["min_without"] in ("a", "c")


def test_run_skips_a_scene_whose_data_is_absent(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("scenes:\n- {name: far, role: evaluation, kind: outdoor, licence: x, local: /nonexistent/far,\n"
                 "   source: {repo: a/b, commit: '" + "0" * 40 + "', path: .}, convert: [], views: [3]}\n")
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--protocol", str(f), "--records",
                          str(tmp_path / "rec"), "run", "--role", "evaluation", "--work", str(tmp_path / "w")],
                         cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0 and "SKIP far" in out.stdout and "0 runs to do" in out.stdout


def test_a_run_another_process_holds_is_skipped(tmp_path):
    """Two ``run`` commands over overlapping grids: a run whose lock another process holds is
    skipped, with no record; the lock is the system's (``flock``), gone with its holder."""
    from experiments.sparse_views.runs import run_lock

    f = tmp_path / "p.yaml"
    f.write_text("scenes:\n- {name: tiny, role: tuning, kind: synthetic, views: [3],\n"
                 "   generate: [python, -m, camio, synth, --out, '{out}', --views, '16', --width, '128']}\n")
    lock = tmp_path / "w" / "tiny_n3" / "runs" / "tiny_n3_paper_s0_i20.lock"
    with run_lock(lock) as mine:
        assert mine
        out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--protocol", str(f), "--records",
                              str(tmp_path / "rec"), "run", "--role", "tuning", "--recipes", "paper", "--seeds", "0",
                              "--iterations", "20", "--work", str(tmp_path / "w")], cwd=REPO, capture_output=True,
                             text=True)
        assert out.returncode == 0 and "running in another process" in out.stdout, out.stdout + out.stderr
        assert not list((tmp_path / "rec" / "runs").glob("*.json"))
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, sys, time; fh = open(sys.argv[1], 'a'); "
                               "fcntl.flock(fh, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)", str(lock)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with run_lock(lock) as mine:
            assert not mine
    finally:
        holder.kill()
        holder.wait()
    with run_lock(lock) as mine:  # its holder killed: free again
        assert mine


def test_run_trains_scores_and_records_through_the_stage_commands(tmp_path):
    """``run`` on a small generated scene: the cell is prepared by the stage commands, one run
    trained and scored, and its record holds the table's keys; a second ``run`` finds the record
    and trains nothing."""
    f = tmp_path / "p.yaml"
    f.write_text("scenes:\n- {name: tiny, role: tuning, kind: synthetic, views: [3],\n"
                 "   generate: [python, -m, camio, synth, --out, '{out}', --views, '16', --width, '128']}\n")
    cmd = [sys.executable, "-m", "experiments.sparse_views", "--protocol", str(f), "--records", str(tmp_path / "rec"),
           "run", "--role", "tuning", "--recipes", "paper", "--seeds", "0", "--iterations", "20",
           "--work", str(tmp_path / "w")]
    t0 = datetime.now(timezone.utc).replace(microsecond=0)
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
    (rec_path,) = (tmp_path / "rec" / "runs").glob("*.json")
    rec = json.loads(rec_path.read_text())
    assert rec_path.name == "tiny_n3_paper_s0_i20.json" and set(RECORD_KEYS) <= set(rec)
    # when the run began, in UTC: the clock a registration's commit is checked against
    assert t0 <= datetime.fromisoformat(rec["started_at"]) <= datetime.now(timezone.utc)
    assert rec["role"] == "tuning" and rec["iterations"] == 20 and rec["gaussians"] > 0
    assert 5 < rec["psnr"] < 60 and 0 < rec["ssim"] <= 1 and rec["curve"]["psnr"]
    again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    assert again.returncode == 0 and "0 runs to do" in again.stdout
    # the GPU check's backend comparison, on the CPU against itself: the cell packed by its CLI,
    # the run trained again and set beside this record (same kernel and seed: the same result)
    pack = subprocess.run([sys.executable, "-m", "benchmarks.backend_agree", "pack", str(tmp_path / "packed"), "--scene",
                           "tiny", "--protocol", str(f), "--work", str(tmp_path / "w")],
                          cwd=REPO, capture_output=True, text=True)
    assert pack.returncode == 0, pack.stderr
    assert json.loads((tmp_path / "packed" / "cell.json").read_text())["name"] == "tiny_n3"
    again = subprocess.run(pack.args, cwd=REPO, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr  # its own folder: packed again in place
    # never over an input, never into a folder it did not write: one line, nothing changed
    for dest in (tmp_path / "w", tmp_path / "rec"):
        before = sorted(p.name for p in dest.iterdir())
        bad = subprocess.run([*pack.args[:4], str(dest), *pack.args[5:]], cwd=REPO, capture_output=True, text=True)
        assert bad.returncode == 2 and "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
        assert sorted(p.name for p in dest.iterdir()) == before
    agree = backend_agree(tmp_path / "packed", "tiny_n3", device="cpu", rasterizer="cpu", runs=(("paper", 0),),
                          iterations=20, records=tmp_path / "rec" / "runs")
    (run,) = agree["runs"]
    assert run["record"]["path"] == rec_path.name and run["record"]["backend"] == run["this"]["backend"] == "cpu"
    assert run["this"]["at_iteration"] == run["record"]["at_iteration"] == 20
    assert abs(run["psnr_diff"]) < 0.05 and agree["by_recipe"]["paper"]["seeds"] == [0]
    # each of gsplat's semantics emulated on the CPU kernel, through its command line
    sem = subprocess.run([sys.executable, "-m", "benchmarks.backend_semantics", "--cell", str(tmp_path / "packed"),
                          "--variants", "cpu", "visibility", "--seeds", "0", "--iterations", "20", "--records",
                          str(tmp_path / "rec" / "runs"), "--out", str(tmp_path / "sem.json")],
                         cwd=REPO, capture_output=True, text=True)
    assert sem.returncode == 0, sem.stderr
    summary = json.loads((tmp_path / "sem.json").read_text())["summary"]
    assert summary["cpu"]["seeds"] == summary["visibility"]["seeds"] == 1
    assert 5 < summary["visibility"]["mean"] < 60 and "minus_cpu" in summary["visibility"]
    from experiments.results_doc.gpu_table import format_gpu_table

    assert "| cpu vs the grid's CPU records, tiny_n3 20 it, paper, seeds [0]: final held-out PSNR |" in \
        format_gpu_table({"backend_agree": agree})
    # the same name with other recipe values: the kept record, then (record removed) the kept
    # model, are refused by name, never reused
    changed = [*cmd[:cmd.index("paper")], 'paper={"recipe": "paper", "densify_grad_threshold": 0.001}',
               *cmd[cmd.index("paper") + 1:]]
    stale = subprocess.run(changed, cwd=REPO, capture_output=True, text=True)
    assert stale.returncode == 2 and "densify_grad_threshold" in stale.stderr and "remove it" in stale.stderr
    rec_path.unlink()
    stale = subprocess.run(changed, cwd=REPO, capture_output=True, text=True)
    assert stale.returncode == 2 and "densify_grad_threshold" in stale.stderr and "remove the folder" in stale.stderr
    assert "Traceback" not in stale.stderr and not rec_path.exists()


@pytest.mark.slow
def test_a_dense_seed_reaches_the_bridge_at_its_own_stride(tmp_path):
    """A cell seeded by mvs: the initialiser runs once for every Bridge choice; the Bridge reads
    its full map at the Bridge's own stride unless a variant names another one."""
    from experiments.sparse_views.cells import prepare
    from experiments.sparse_views.protocol import Scene
    from bridge.core import BridgeConfig

    scene = Scene("tiny", "tuning", "synthetic", (3,),
                  generate=("python", "-m", "camio", "synth", "--out", "{out}", "--views", "16", "--width", "128"))
    own = prepare(tmp_path / "tiny_n3", scene, 3, "mvs", "gated")
    other = prepare(tmp_path / "tiny_n3", scene, 3, "mvs", "gated", 4)
    assert own["bridge"].parent.name == "seed_mvs_gated" and other["bridge"].parent.name == "seed_mvs_gated_stride4"
    b1, b4 = (json.loads((c["bridge"] / "bridge.json").read_text()) for c in (own, other))
    assert b1["stride"] == BridgeConfig().stride == 20 and b4["stride"] == 4
    assert b4["points_kept"] > 3 * b1["points_kept"] > 0  # the same map, every 4th pixel against every 20th
    log = (tmp_path / "tiny_n3" / "prepare.log").read_text()
    assert log.count("$ -m evaluation.initialisers.mvs ") == 1  # one stereo run for both


# the colour the stand-in trainer resolves a "mean" background to
MEAN_STAND_IN = [0.25, 0.5, 0.75]


def _empty_cell(work, scene, n, init="posed", mode=None, stride=None, init_args=None):
    """A stand-in for the cell's preparation: its folders, no test views."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "test.txt").write_text("")
    return {k: work / k for k in ("scene", "bridge", "align")} | {"train": work / "train.txt",
                                                                   "test": work / "test.txt"}


def _stand_in_stages(monkeypatch, calls, prepare):
    """The grid's stage commands replaced: each is recorded in ``calls`` and leaves what the
    next step reads (train.json with the config it got, its background black unless given, "mean"
    resolved to :data:`MEAN_STAND_IN`, a metrics file); ``prepare`` stands for the cell's preparation, and
    every recipe resolves no values."""
    from experiments.sparse_views import cells, runs

    def stage(args, log):
        calls.append(args)
        if args[:2] == ["-m", "splat_train"] and args[2] != "render":
            out = Path(args[args.index("--out") + 1])
            out.mkdir(parents=True, exist_ok=True)
            cfg = {"background": [0.0, 0.0, 0.0], **json.loads(args[args.index("--config") + 1])}  # paper's black
            if cfg.get("background") == "mean":  # the trainer resolves it and keeps the colour
                cfg["background"] = MEAN_STAND_IN
            (out / "train.json").write_text(json.dumps({"config": cfg, "num_gaussians": 1, "wall_time_s": 1.0}))
        if args[:3] == ["-m", "evaluation", "images"]:
            Path(args[args.index("--out") + 1]).write_text(json.dumps({"psnr": 20.0, "ssim": 0.5, "lpips_alex": 0.3,
                                                                       "lpips_vgg": 0.4}))

    monkeypatch.setattr(runs, "sh", stage)
    monkeypatch.setattr(runs, "resolved_values", lambda *a: {})
    monkeypatch.setattr(cells, "prepare", prepare)


def test_a_scene_background_reaches_training_and_the_held_out_renders(tmp_path, monkeypatch):
    """A scene whose images are composited on white (scenes.yaml ``background: [1, 1, 1]``, as
    NeRF-synthetic's) trains and renders every recipe against white; others stay black."""
    from experiments.sparse_views import __main__ as cli

    f = tmp_path / "p.yaml"
    f.write_text("scenes:\n- {name: white, role: tuning, kind: synthetic, views: [3], background: [1, 1, 1],\n"
                 "   generate: [python, -m, camio, synth, --out, '{out}']}\n"
                 "- {name: black, role: tuning, kind: synthetic, views: [3],\n"
                 "   generate: [python, -m, camio, synth, --out, '{out}']}\n")
    assert [s.background for s in protocol.load(f)] == [(1.0, 1.0, 1.0), None]  # None: the trainer's black
    calls = []

    _stand_in_stages(monkeypatch, calls, _empty_cell)
    assert cli.main(["--protocol", str(f), "--records", str(tmp_path / "rec"), "run", "--role", "tuning",
                     "--recipes", "paper", "--seeds", "0", "--iterations", "20", "--work", str(tmp_path / "w")]) == 0
    train = [c for c in calls if c[:2] == ["-m", "splat_train"] and c[2] != "render"]
    render = [c for c in calls if c[:3] == ["-m", "splat_train", "render"]]
    assert [json.loads(c[c.index("--config") + 1]).get("background") for c in train] == [[1.0, 1.0, 1.0], None]
    # the black scene renders with the renderer's own default, black, as it trained
    assert [c[c.index("--background") + 1] if "--background" in c else None for c in render] == ["1.0,1.0,1.0", None]
    rec = json.loads((tmp_path / "rec" / "runs" / "white_n3_paper_s0_i20.json").read_text())
    assert rec["config"] == {"recipe": "paper", "background": [1.0, 1.0, 1.0]}
    # every record keeps the colour its run trained and rendered against
    assert rec["background"] == [1.0, 1.0, 1.0]
    rec = json.loads((tmp_path / "rec" / "runs" / "black_n3_paper_s0_i20.json").read_text())
    assert rec["config"] == {"recipe": "paper"} and rec["background"] == [0.0, 0.0, 0.0]


def test_a_variant_against_the_training_views_mean_colour(tmp_path, monkeypatch):
    """``"background": "mean"`` reaches the trainer as it is; the colour the trainer resolved
    it to (train.json's config) is the one the held-out renders use and the record keeps; a
    scene's own background stands instead (tests/test_train_background.py: the trainer's side)."""
    from experiments.sparse_views import __main__ as cli

    f = tmp_path / "p.yaml"
    f.write_text("scenes:\n- {name: plain, role: tuning, kind: synthetic, views: [3],\n"
                 "   generate: [python, -m, camio, synth, --out, '{out}']}\n"
                 "- {name: white, role: tuning, kind: synthetic, views: [3], background: [1, 1, 1],\n"
                 "   generate: [python, -m, camio, synth, --out, '{out}']}\n")
    calls = []

    _stand_in_stages(monkeypatch, calls, _empty_cell)
    assert cli.main(["--protocol", str(f), "--records", str(tmp_path / "rec"), "run", "--role", "tuning",
                     "--recipes", 'paper-bgmean={"recipe": "paper", "background": "mean"}', "--seeds", "0",
                     "--iterations", "20", "--work", str(tmp_path / "w")]) == 0
    train = [c for c in calls if c[:2] == ["-m", "splat_train"] and c[2] != "render"]
    render = [c for c in calls if c[:3] == ["-m", "splat_train", "render"]]
    assert [json.loads(c[c.index("--config") + 1])["background"] for c in train] == ["mean", [1.0, 1.0, 1.0]]
    assert [c[c.index("--background") + 1] for c in render] == ["0.25,0.5,0.75", "1.0,1.0,1.0"]
    rec = json.loads((tmp_path / "rec" / "runs" / "plain_n3_paper-bgmean_s0_i20.json").read_text())
    assert rec["config"] == {"recipe": "paper", "background": "mean"} and rec["background"] == MEAN_STAND_IN


@pytest.mark.parametrize("bad", ["2/2", "1", "a/b", "0/0", "-1/2"])
def test_run_refuses_a_bad_shard_in_one_line(tmp_path, bad):
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--records", str(tmp_path / "rec"), "run",
                          "--role", "evaluation", "--work", str(tmp_path / "w"), f"--shard={bad}"],
                         cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 2 and "--shard must be K/M" in out.stderr and "Traceback" not in out.stderr


def test_a_cell_seeds_from_the_random_fallback_only_when_its_views_triangulate_no_point(tmp_path):
    from experiments.sparse_views.cells import seed_model

    init = tmp_path / "posed"
    init.mkdir()
    assert seed_model(init) == init / "sparse" / "0"  # no status: the triangulated model
    fallback = {"applied": True, "model": "random_fallback/sparse/0", "points_found": 0}
    (init / "status.json").write_text(json.dumps({"points": 12, "fallback": {**fallback, "points_found": 12}}))
    assert seed_model(init) == init / "sparse" / "0"  # few points are still measured geometry
    (init / "status.json").write_text(json.dumps({"points": 0, "fallback": fallback}))
    assert seed_model(init) == init / "random_fallback" / "sparse" / "0"


def test_backend_comparison_runs_are_seed_major_and_bad_lists_are_refused():
    from benchmarks.backend_agree import RUNS, parse_runs

    assert parse_runs("0-2", "sparse,paper")[:3] == (("sparse", 0), ("paper", 0), ("sparse", 1))
    assert parse_runs("0,3-4", "sparse") == (("sparse", 0), ("sparse", 3), ("sparse", 4))
    assert set(parse_runs("0-2")) == set(RUNS)
    for seeds, recipes in (("x", "paper"), ("3-1", "paper"), ("0", "nope"), ("", "paper")):
        with pytest.raises(ValueError):
            parse_runs(seeds, recipes)


def test_backend_comparison_against_every_record_of_the_recipe(tmp_path):
    """attach_records pairs runs by seed and also sets them against every record of the same
    cell, recipe and iterations (other seeds, unpaired: Welch), never against another recipe."""
    from benchmarks.backend_agree import attach_records
    from evaluation.study.stats import welch_interval

    cpu = {0: 21.0, 1: 21.4, 2: 20.9, 3: 21.3}
    for seed, psnr in cpu.items():
        rec = {"recipe": "sparse", "curve": {"iterations": [10, 20], "psnr": [15.0, psnr]}, "backend": "cpu"}
        (tmp_path / f"c_n3_sparse_s{seed}_i20.json").write_text(json.dumps(rec))
    (tmp_path / "c_n3_paper_s0_i20.json").write_text(json.dumps({"recipe": "paper", "curve": {"psnr": [9.0]}}))
    runs = [{"recipe": "sparse", "seed": s, "this": {"psnr": p}} for s, p in ((0, 20.5), (1, 20.9))]
    res = attach_records({"cell": "c_n3", "iterations": 20, "runs": runs}, tmp_path)
    assert [r["psnr_diff"] for r in res["runs"]] == [pytest.approx(-0.5), pytest.approx(-0.5)]
    a = res["by_recipe"]["sparse"]["all_records"]
    diff, hw, _df = welch_interval([20.5, 20.9], list(cpu.values()))
    assert a["seeds"] == 4 and a["psnr_diff"] == pytest.approx(diff) and a["psnr_diff_hw95"] == pytest.approx(hw)


def test_every_shipped_record_of_a_recipe_matches_what_the_recipe_resolves_now():
    """A record whose kept values differ from its recipe's stops `run` (exit 2, "made with other
    values"): the shipped records of the four recipes, and of the variants that keep a recipe's
    earlier values (paper-seedcode, dropgaussian-wsprune, mcmc-keep), must stay current when a
    recipe gains a key, or rerunning the README's grid fails on them. Records from before values
    were recorded (the first tuning round's) say so and are left out."""
    from experiments.sparse_views.runs import resolved_values, stale_keys
    from splat_train.recipes import RECIPE_NAMES, VARIANTS

    records = sorted((protocol.REPO / "experiments" / "records" / "sparse_views" / "runs").glob("*.json"))
    checked, by_name = 0, {}
    for path in records:
        rec = json.loads(path.read_text())
        if (rec["recipe"] not in RECIPE_NAMES and rec["recipe"] not in VARIANTS) or rec.get("values") is None:
            continue
        assert rec["config"]["recipe"] == rec["recipe"], path.name
        overrides = {k: v for k, v in (rec.get("config") or {}).items() if k != "recipe"}
        want = resolved_values(rec["recipe"], overrides, rec["iterations"])
        assert stale_keys(rec["values"], want) == [], path.name
        checked += 1
        by_name[rec["recipe"]] = by_name.get(rec["recipe"], 0) + 1
    assert checked >= 500
    assert all(by_name.get(v, 0) >= 90 for v in VARIANTS), by_name


def test_a_key_older_records_predate_counts_at_the_value_their_runs_had():
    from experiments.sparse_views.runs import stale_keys

    want = {"dropout_rate": 0.2, "dropout_ramp_fraction": 1.0}
    assert stale_keys({"dropout_rate": 0.2}, want) == []  # made before the ramp was a key: ramp 1
    assert stale_keys({"dropout_rate": 0.2}, {**want, "dropout_ramp_fraction": 0.3}) == ["dropout_ramp_fraction"]
    assert stale_keys({"dropout_rate": 0.2}, {**want, "depth_weight": 0.05}) == ["depth_weight"]


def test_a_run_against_the_mean_colour_is_told_apart_from_one_against_a_colour():
    """The recipe's background is a value like the others: a kept run trained against black
    is stale for a recipe or variant that asks for the mean colour (and the other way round),
    while train.json keeps the resolved colour and, in ``background_from``, that it was the mean."""
    from experiments.sparse_views.runs import resolved_values, stale_keys, train_values

    black, mean = resolved_values("paper", {}, 300), resolved_values("paper", {"background": "mean"}, 300)
    assert resolved_values("sparse", {}, 300)["background"] == "mean"
    assert resolved_values("sparse", {"background": [0, 0, 0]}, 300)["background"] == [0.0, 0.0, 0.0]
    assert black["background"] == [0.0, 0.0, 0.0] and mean["background"] == "mean"
    tj = {"config": {**black, "background": [0.4, 0.5, 0.6]}, "background_from": "mean"}
    assert stale_keys(train_values(tj), mean) == []
    assert stale_keys(train_values(tj), black) == ["background"]
    assert stale_keys(train_values({"config": black}), mean) == ["background"]
    # a record from before the key ran on black
    assert stale_keys({k: v for k, v in black.items() if k != "background"}, black) == []
    assert stale_keys({k: v for k, v in black.items() if k != "background"}, mean) == ["background"]


def _summary(tmp_path, doc: Path) -> subprocess.CompletedProcess:
    runs = tmp_path / "rec" / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    (runs / "0.json").write_text(json.dumps(_rec("a", "evaluation", "sparse", 0, 20.0, 0.2)))
    return subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--records", str(tmp_path / "rec"),
                           "summary", "--doc", str(doc)], cwd=REPO, capture_output=True, text=True)


def test_summary_doc_replaces_only_a_table_it_wrote(tmp_path):
    """``summary --doc FILE`` writes a new file or one it generated before (its "Generated by"
    line); any other file, or a link, is refused with one line and left as it was."""
    from _cli import refused

    doc = tmp_path / "table.md"
    assert _summary(tmp_path, doc).returncode == 0
    first = doc.read_text()
    assert _summary(tmp_path, doc).returncode == 0 and doc.read_text() == first  # its own: replaced
    mine = tmp_path / "notes.md"
    mine.write_text("# my notes\n")
    refused(_summary(tmp_path, mine), str(mine), "was not written by this command")
    assert mine.read_text() == "# my notes\n"
    link = tmp_path / "link.md"
    link.symlink_to(doc)
    refused(_summary(tmp_path, link), str(link), "symbolic link")
    assert link.is_symlink() and doc.read_text() == first


@pytest.mark.parametrize("select, needles", [
    (["--scenes", "dekс"], ["--scenes dekс", "known: desk, lamp"]),
    (["--scenes", "desk", "lamb"], ["--scenes lamb", "known: desk, lamp"]),
    (["--scenes", "fern"], ["--scenes fern", "role evaluation", "known: desk, lamp"]),
    (["--n", "7"], ["--n 7", "known: 3, 6"]),
    (["--scenes"], ["(none given)"]),
])
def test_run_refuses_a_selection_that_matches_nothing(tmp_path, select, needles):
    """A misspelt scene or a view count the scenes do not have: exit 2 naming the unknown and
    the known values, never "0 runs to do"."""
    from _cli import refused

    f = tmp_path / "p.yaml"
    f.write_text("scenes:\n- {name: desk, role: evaluation, kind: indoor, views: [3], local: /nonexistent/desk}\n"
                 "- {name: lamp, role: evaluation, kind: indoor, views: [3, 6], local: /nonexistent/lamp}\n"
                 "- {name: fern, role: tuning, kind: indoor, views: [3], local: /nonexistent/fern}\n")
    out = subprocess.run([sys.executable, "-m", "experiments.sparse_views", "--protocol", str(f), "--records",
                          str(tmp_path / "rec"), "run", "--role", "evaluation", "--work", str(tmp_path / "w"),
                          *select], cwd=REPO, capture_output=True, text=True)
    refused(out, *needles)
    assert "runs to do" not in out.stdout and not (tmp_path / "rec").exists()
