"""``python -m experiments.sparse_views relabel``: when a value lands, the recipe's old records
become a variant and the candidate's the recipe's, each checked against the recipe as it is
then, so that no record carries a name whose values it was not trained with."""

import json

from dataclasses import replace

import pytest

from experiments.sparse_views.__main__ import main
from experiments.sparse_views.runs import resolved_values, run_name
from splat_train.recipes import BACKGROUND_BLACK, BACKGROUND_MEAN, RECIPES

ITS = 300


def _write(runs, scene, name, cfg, values, psnr):
    rec = {"scene": scene, "role": "tuning", "n": 3, "recipe": name, "seed": 0, "iterations": ITS, "psnr": psnr,
           "ssim": 0.5, "lpips_alex": 0.4, "lpips_vgg": 0.5, "gaussians": 100, "train_s": 1.0, "backend": "cpu",
           "config": cfg, "values": values}
    path = runs / f"{run_name(scene, 3, name, 0, ITS)}.json"
    path.write_text(json.dumps(rec, indent=1) + "\n")
    return path


def _set_sparse_background(monkeypatch, colour):
    """The ``sparse`` recipe with another background, for the test's duration."""
    sparse = RECIPES["sparse"]
    monkeypatch.setitem(RECIPES, "sparse", replace(sparse, optim=replace(sparse.optim, background=colour)))


@pytest.fixture
def records(tmp_path, monkeypatch):
    """fern (black behind its runs) and the milk carton (white, its scenes.yaml background):
    `sparse` and the candidate `sparse-bgmean` on each, as the grid writes them while `sparse`
    trains against black."""
    _set_sparse_background(monkeypatch, BACKGROUND_BLACK)
    runs = tmp_path / "records" / "runs"
    runs.mkdir(parents=True)
    mean = {"recipe": "sparse", "background": BACKGROUND_MEAN}
    white = {"background": [1.0, 1.0, 1.0]}
    _write(runs, "llff__fern", "sparse", {"recipe": "sparse"}, resolved_values("sparse", {}, ITS), 15.0)
    _write(runs, "llff__fern", "sparse-bgmean", mean, resolved_values("sparse", {"background": "mean"}, ITS), 16.0)
    _write(runs, "own__milk", "sparse", {"recipe": "sparse", **white}, resolved_values("sparse", white, ITS), 17.0)
    _write(runs, "own__milk", "sparse-bgmean", {**mean, **white}, resolved_values("sparse", white, ITS), 17.0)
    return tmp_path / "records"


def _names(records):
    return sorted(p.name for p in (records / "runs").glob("*.json"))


def _cli(records, *args):
    return main(["--records", str(records), "relabel", *args])


def test_a_candidate_is_refused_the_recipe_name_before_the_recipe_takes_its_value(records, capsys):
    before = _names(records)
    (records / "runs" / f"{run_name('llff__fern', 3, 'sparse', 0, ITS)}.json").unlink()  # its name free
    before.remove(f"{run_name('llff__fern', 3, 'sparse', 0, ITS)}.json")
    assert _cli(records, "sparse-bgmean", "sparse") == 2  # sparse trains against black here
    assert "were not trained with what recipe 'sparse' gives now" in capsys.readouterr().err
    assert _names(records) == before
    assert _cli(records, "sparse", "sparse-r13", "--stale-only") == 0  # sparse's own records are current
    assert "0 records" in capsys.readouterr().out and _names(records) == before


def test_landing_a_value_moves_the_stale_records_aside_and_the_candidate_in(records, monkeypatch, tmp_path, capsys):
    work = tmp_path / "work"
    for scene in ("llff__fern", "own__milk"):
        for name in ("sparse", "sparse-bgmean"):
            folder = work / f"{scene}_n3" / "runs" / run_name(scene, 3, name, 0, ITS)
            folder.mkdir(parents=True)
            (folder / "train.json").write_text(json.dumps({"name": name}))
    white = {"background": [1.0, 1.0, 1.0]}  # a white scene with the candidate's run alone
    _write(records / "runs", "blender__lego", "sparse-bgmean", {"recipe": "sparse", **white},
           resolved_values("sparse", white, ITS), 18.0)
    _set_sparse_background(monkeypatch, BACKGROUND_MEAN)  # the value lands
    # the candidate cannot take the name while fern's old record holds it
    assert _cli(records, "sparse-bgmean", "sparse", "--work", str(work)) == 2
    assert "exists already" in capsys.readouterr().err
    assert _cli(records, "sparse", "sparse-r13", "--stale-only", "--work", str(work)) == 0
    assert "1 records of 'sparse' are now 'sparse-r13'" in capsys.readouterr().out
    # the milk carton's white still is what sparse gives there: its record keeps the name
    assert (records / "runs" / f"{run_name('own__milk', 3, 'sparse', 0, ITS)}.json").is_file()
    assert _cli(records, "sparse-bgmean", "sparse", "--work", str(work)) == 2  # the milk's name is taken
    (records / "runs" / f"{run_name('own__milk', 3, 'sparse-bgmean', 0, ITS)}.json").unlink()
    assert _cli(records, "sparse-bgmean", "sparse", "--work", str(work)) == 0
    runs = records / "runs"
    old = json.loads((runs / f"{run_name('llff__fern', 3, 'sparse-r13', 0, ITS)}.json").read_text())
    new = json.loads((runs / f"{run_name('llff__fern', 3, 'sparse', 0, ITS)}.json").read_text())
    assert (old["recipe"], old["psnr"], old["config"]) == ("sparse-r13", 15.0, {"recipe": "sparse"})
    assert (new["recipe"], new["psnr"], new["config"]) == ("sparse", 16.0, {"recipe": "sparse"})
    assert new["values"]["background"] == BACKGROUND_MEAN
    # its config as a run of sparse writes it there, with the scene's own colour
    lego = json.loads((runs / f"{run_name('blender__lego', 3, 'sparse', 0, ITS)}.json").read_text())
    assert (lego["recipe"], lego["config"]) == ("sparse", {"recipe": "sparse", "background": [1.0, 1.0, 1.0]})
    assert _names(records) == sorted(f"{run_name(s, 3, r, 0, ITS)}.json" for s, r in
                                     [("llff__fern", "sparse"), ("llff__fern", "sparse-r13"), ("own__milk", "sparse"),
                                      ("blender__lego", "sparse")])
    cell = work / "llff__fern_n3" / "runs"
    assert json.loads((cell / run_name("llff__fern", 3, "sparse-r13", 0, ITS) / "train.json").read_text()) == \
        {"name": "sparse"}
    assert json.loads((cell / run_name("llff__fern", 3, "sparse", 0, ITS) / "train.json").read_text()) == \
        {"name": "sparse-bgmean"}


def test_bad_requests_say_why_and_move_nothing(records, capsys):
    before = _names(records)
    assert _cli(records, "sparse-nothing", "sparse-r13") == 2
    assert "no record" in capsys.readouterr().err
    assert _cli(records, "sparse-bgmean", "sparse-r13", "--stale-only") == 2
    assert "not a recipe" in capsys.readouterr().err
    assert _cli(records, "sparse", "sparse") == 2
    assert _names(records) == before


def test_a_recipes_old_records_become_its_kept_variant_checked_against_it(tmp_path, capsys):
    """``paper``'s records made with the seed code's schedule move to ``paper-seedcode`` (a kept
    variant, splat_train.recipes.VARIANTS), whose values they must have; a record that predates
    its values is judged on its schedule; records of other values are refused the name."""
    records = tmp_path / "records"
    runs = records / "runs"
    runs.mkdir(parents=True)
    old = resolved_values("paper-seedcode", {}, ITS)
    assert old != resolved_values("paper", {}, ITS)
    _write(runs, "llff__fern", "paper", {"recipe": "paper"}, old, 15.0)
    sched = {k: old[k] for k in ("densify_from", "densify_until", "densify_every", "opacity_reset_every",
                                 "sh_increase_every")}
    early = _write(runs, "llff__horns", "paper", {"recipe": "paper"}, None, 14.0)
    early.write_text(json.dumps({**json.loads(early.read_text()), "schedule": sched}))
    _write(runs, "llff__room", "dropgaussian", {"recipe": "dropgaussian"}, resolved_values("dropgaussian", {}, ITS), 16.0)
    assert _cli(records, "dropgaussian", "dropgaussian-wsprune") == 2  # trained without the prune
    assert "were not trained with what variant 'dropgaussian-wsprune' gives now" in capsys.readouterr().err
    assert _cli(records, "paper", "paper-seedcode", "--stale-only") == 0
    assert "2 records of 'paper' are now 'paper-seedcode'" in capsys.readouterr().out
    for scene, psnr in (("llff__fern", 15.0), ("llff__horns", 14.0)):
        rec = json.loads((runs / f"{run_name(scene, 3, 'paper-seedcode', 0, ITS)}.json").read_text())
        assert (rec["recipe"], rec["config"], rec["psnr"]) == ("paper-seedcode", {"recipe": "paper-seedcode"}, psnr)
    fern = json.loads((runs / f"{run_name('llff__fern', 3, 'paper-seedcode', 0, ITS)}.json").read_text())
    assert fern["values"] == old


def test_variants_built_on_a_recipe_name_its_kept_variant_only_when_their_values_are_its(tmp_path, capsys):
    """``--built-on``: a variant built on ``paper`` (``paper-mvs``, ``{"recipe": "paper", "init":
    "mvs"}``) trained with paper's earlier values keeps its name and its seed keys, and its config
    names ``paper-seedcode``; one trained with other values refuses the move, and nothing moves."""
    runs = tmp_path / "records" / "runs"
    runs.mkdir(parents=True)
    seedcode = resolved_values("paper-seedcode", {}, ITS)
    old = _write(runs, "llff__fern", "paper", {"recipe": "paper"}, seedcode, 14.0)
    mvs = _write(runs, "llff__fern", "paper-mvs", {"recipe": "paper", "init": "mvs", "bridge_mode": "gated"},
                 seedcode, 15.0)
    odd = _write(runs, "llff__horns", "paper-mvs", {"recipe": "paper", "init": "mvs"},
                 {**seedcode, "densify_every": 7}, 15.0)
    before = {p.name: p.read_text() for p in runs.glob("*.json")}
    assert _cli(tmp_path / "records", "paper", "paper-seedcode", "--stale-only", "--built-on") == 2
    err = capsys.readouterr().err
    assert "nothing moved" in err and odd.name in err and len(err.strip().splitlines()) == 1
    assert {p.name: p.read_text() for p in runs.glob("*.json")} == before
    odd.unlink()
    assert _cli(tmp_path / "records", "paper", "paper-seedcode", "--stale-only", "--built-on") == 0
    assert not old.exists()
    moved = json.loads((runs / f"{run_name('llff__fern', 3, 'paper-seedcode', 0, ITS)}.json").read_text())
    assert moved["recipe"] == "paper-seedcode" and moved["config"] == {"recipe": "paper-seedcode"}
    built = json.loads(mvs.read_text())
    assert built["recipe"] == "paper-mvs"
    assert built["config"] == {"recipe": "paper-seedcode", "init": "mvs", "bridge_mode": "gated"}
    assert resolved_values(built["config"]["recipe"], {}, ITS) == built["values"]


# --- reconfig: a record's config says what a run of its values is asked now -------------------

def _reconfig(records, name, config):
    from tests._cli import run

    return run(["-m", "experiments.sparse_views", "--records", str(records), "reconfig", name, "--config", config])


def _texts(runs):
    return {p.name: p.read_text() for p in sorted(runs.glob("*.json"))}


@pytest.fixture
def old_records(tmp_path):
    """``sparse-r13`` (trained against black, filed with config ``{"recipe": "sparse"}``) on fern
    and on the milk carton (white, its scenes.yaml background), and ``mcmc-r13`` (``mcmc-keep``'s
    values from before the ``mcmc_growth`` key, filed as ``{"recipe": "mcmc"}``) on fern."""
    runs = tmp_path / "records" / "runs"
    runs.mkdir(parents=True)
    white = {"background": [1.0, 1.0, 1.0]}
    _write(runs, "llff__fern", "sparse-r13", {"recipe": "sparse"},
           resolved_values("sparse", {"background": [0.0, 0.0, 0.0]}, ITS), 15.0)
    _write(runs, "own__milk", "sparse-r13", {"recipe": "sparse"}, resolved_values("sparse", white, ITS), 17.0)
    keep = resolved_values("mcmc-keep", {"mcmc_growth": "gsplat"}, ITS)
    assert keep != resolved_values("mcmc", {}, ITS)
    _write(runs, "llff__fern", "mcmc-r13", {"recipe": "mcmc"}, {k: v for k, v in keep.items() if k != "mcmc_growth"},
           16.0)
    return tmp_path / "records"


def test_reconfig_sets_the_config_that_gives_each_records_values(old_records):
    """``reconfig NAME --config JSON``: every record of NAME keeps its name and figures, and its
    config becomes JSON (with the scene's own background where scenes.yaml gives one); a record
    that predates a key counts at its implied value (``mcmc_growth`` "gsplat"); run again, it
    changes nothing."""
    runs = old_records / "runs"
    before = {p.name: json.loads(p.read_text()) for p in runs.glob("*.json")}
    proc = _reconfig(old_records, "sparse-r13", '{"recipe": "sparse", "background": [0, 0, 0]}')
    assert proc.returncode == 0, proc.stderr
    assert "2 of 2 records of 'sparse-r13' now have config" in proc.stdout
    assert "1 with their scene's own background" in proc.stdout
    proc = _reconfig(old_records, "mcmc-r13", '{"recipe": "mcmc-keep", "mcmc_growth": "gsplat"}')
    assert proc.returncode == 0, proc.stderr
    after = {p.name: json.loads(p.read_text()) for p in runs.glob("*.json")}
    assert set(after) == set(before)
    for name, rec in after.items():  # the config alone changed
        assert {k: v for k, v in rec.items() if k != "config"} == {k: v for k, v in before[name].items() if k != "config"}
    fern = after[f"{run_name('llff__fern', 3, 'sparse-r13', 0, ITS)}.json"]
    milk = after[f"{run_name('own__milk', 3, 'sparse-r13', 0, ITS)}.json"]
    mcmc = after[f"{run_name('llff__fern', 3, 'mcmc-r13', 0, ITS)}.json"]
    assert fern["config"] == {"recipe": "sparse", "background": [0, 0, 0]}
    assert milk["config"] == {"recipe": "sparse", "background": [1.0, 1.0, 1.0]}
    assert mcmc["config"] == {"recipe": "mcmc-keep", "mcmc_growth": "gsplat"}
    for rec in after.values():  # what the config asks is what the record was trained with
        cfg = {k: v for k, v in rec["config"].items() if k != "recipe"}
        assert resolved_values(rec["config"]["recipe"], cfg, ITS) == {**resolved_values(
            rec["config"]["recipe"], cfg, ITS), **rec["values"]}
    texts = _texts(runs)
    proc = _reconfig(old_records, "sparse-r13", '{"recipe": "sparse", "background": [0, 0, 0]}')
    assert proc.returncode == 0 and "0 of 2 records" in proc.stdout and "2 had it already" in proc.stdout
    assert _texts(runs) == texts


def test_reconfig_refuses_one_mismatch_and_writes_nothing(old_records):
    """One record of the name whose values the config does not give (another densification
    period), and the refusal names it: exit 2, one line, no record touched."""
    from tests._cli import refused

    runs = old_records / "runs"
    odd = _write(runs, "llff__horns", "sparse-r13", {"recipe": "sparse"},
                 {**resolved_values("sparse", {"background": [0.0, 0.0, 0.0]}, ITS), "densify_every": 7}, 14.0)
    before = _texts(runs)
    refused(_reconfig(old_records, "sparse-r13", '{"recipe": "sparse", "background": [0, 0, 0]}'),
            "1 of 3 record(s) of 'sparse-r13'", odd.name, "nothing written")
    # mcmc's own name no longer gives mcmc-r13's values (it grows a seed that fills the cap)
    refused(_reconfig(old_records, "mcmc-r13", '{"recipe": "mcmc"}'), "were not trained with what")
    # the growth rule its records predate is not mcmc-keep's now
    refused(_reconfig(old_records, "mcmc-r13", '{"recipe": "mcmc-keep"}'), "were not trained with what")
    # a seed other than the records' is not what they ran from
    refused(_reconfig(old_records, "mcmc-r13", '{"recipe": "mcmc-keep", "mcmc_growth": "gsplat", "init": "mvs"}'),
            "were not trained with what")
    assert _texts(runs) == before


@pytest.mark.parametrize("name, config, needle", [
    pytest.param("sparse-r99", '{"recipe": "sparse"}', "no record in", id="unknown-name"),
    pytest.param("sparse-r13", '{"recipe": "sparse"', "is not JSON", id="not-json"),
    pytest.param("sparse-r13", '["sparse"]', "JSON object with a \"recipe\"", id="no-recipe"),
    pytest.param("sparse-r13", '{"recipe": "sparce"}', "sparce", id="unknown-recipe"),
    pytest.param("sparse-r13", '{"recipe": "sparse", "backround": [0, 0, 0]}', "backround", id="unknown-key"),
])
def test_reconfig_refuses_an_unknown_name_or_config(old_records, name, config, needle):
    from tests._cli import refused

    before = _texts(old_records / "runs")
    refused(_reconfig(old_records, name, config), needle)
    assert _texts(old_records / "runs") == before


@pytest.mark.parametrize("name, recipe, count", [("sparse-r13", "sparse", 98), ("mcmc-r13", "mcmc-keep", 289)])
def test_the_shipped_records_of_a_former_value_carry_the_config_of_their_values(name, recipe, count):
    """``sparse-r13`` (``sparse`` on black) and ``mcmc-r13`` (``mcmc-keep`` before its growth
    rule): what each record's config asks resolves now to the values it was trained with."""
    from experiments.sparse_views.protocol import REPO
    from experiments.sparse_views.runs import stale_keys

    paths = sorted((REPO / "experiments" / "records" / "sparse_views" / "runs").glob(f"*_{name}_s*.json"))
    assert len(paths) == count
    for path in paths:
        rec = json.loads(path.read_text())
        cfg = {k: v for k, v in rec["config"].items() if k != "recipe"}
        assert rec["config"]["recipe"] == recipe, path.name
        assert stale_keys(rec["values"], resolved_values(recipe, cfg, rec["iterations"])) == [], path.name


# The record names whose configs no config can make resolve to their kept values today; their
# configs are left as they ran. Each entry says why.
UNRESOLVABLE = {
    # trained at 1,000 and 3,000 iterations with different densification ends (to the end of the
    # 1,000-iteration runs, to 1,500 of the 3,000-iteration ones): neither a count (a schedule key
    # is iterations of its run) nor a share of the run gives both
    "sparse-r10": "densify_until differs between its 1,000- and 3,000-iteration records",
    "sparse-r11": "densify_until differs between its 1,000- and 3,000-iteration records",
    # made (all or some) before records kept their values: such a record keeps only its schedule,
    # so nothing can check a config's other values (background, parts) against what it trained with
    "sparse-cap0.03": "its records keep no values, only their schedule",
    "sparse-cap0.1": "3 of its records keep no values, only their schedule",
    "sparse-nocap": "3 of its records keep no values, only their schedule",
}


def test_every_shipped_record_resolves_to_its_values_through_its_config_or_is_named_unresolvable():
    """Every shipped benchmark record's config (its recipe or variant, its own keys, its scene's
    scenes.yaml background) resolves now to the values it was trained with (a record without
    values: to its schedule), but those of the names in :data:`UNRESOLVABLE`; and each of those
    still has a record that does not, so the list names no record that resolves."""
    from experiments.sparse_views import protocol
    from experiments.sparse_views.relabel import _current

    backgrounds = {s.name: s.background for s in protocol.load()}
    paths = sorted((protocol.REPO / "experiments" / "records" / "sparse_views" / "runs").glob("*.json"))
    assert len(paths) > 1000
    stale = {}
    for path in paths:
        rec = json.loads(path.read_text())
        if not _current(rec, rec["config"]["recipe"], backgrounds, schedule_only=True, own=True):
            stale.setdefault(rec["recipe"], []).append(path.name)
    assert {n: p[0] for n, p in stale.items() if n not in UNRESOLVABLE} == {}
    assert sorted(stale) == sorted(UNRESOLVABLE)


def test_the_recipe_studys_paper_runs_have_the_schedule_of_their_name():
    """The recipe study's runs keep only their schedule: its runs of ``paper`` with the seed
    code's schedule are filed as ``paper-seedcode``, and a run filed under either name has what
    that name gives now (:func:`matches` on the schedule)."""
    from experiments.sparse_views.protocol import REPO
    from experiments.sparse_views.relabel import matches

    checked = 0
    for path in sorted((REPO / "experiments" / "records" / "recipe_study").glob("*.json")):
        rec = json.loads(path.read_text())
        for run in rec["runs"]:
            if run["variant"] in ("paper", "paper-seedcode") and run.get("schedule"):
                assert matches(None, run["schedule"], run["variant"], {}, rec["iterations"], schedule_only=True), \
                    (path.name, run["variant"], run["seed"])
                checked += 1
    assert checked >= 6
