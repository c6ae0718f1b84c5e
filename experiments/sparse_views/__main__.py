"""``python -m experiments.sparse_views``: run the sparse-view grid, or rebuild its table.

    run      train every (scene, n, recipe, seed) of one role that has no record yet
    summary  records -> summary.json and the docs table (no training)
    relabel  rename a recipe's or variant's records when a recipe's value lands
    reconfig set the config of a variant's records to what a run of their values is asked now
    floor    score the flat mean-colour image of each cell (records/floors.json; no training)
    list     the protocol's scenes, their role and whether their data is here
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from experiments.sparse_views import protocol
from experiments.sparse_views.protocol import HERE, REPO
from experiments.sparse_views.runs import SEED_KEYS

RECORDS = REPO / "experiments" / "records" / "sparse_views"
DOC = REPO / "docs" / "results-sparse-views.md"
# the field's recipes beside ours, in the table's order
DEFAULT_RECIPES = ("paper", "dropgaussian", "mcmc", "sparse")


def _variant(text: str) -> tuple[str, dict]:
    """``name`` (a recipe) or ``name=JSON`` (a variant: a recipe plus config keys, and
    optionally :data:`SEED_KEYS`: ``init`` the cell's seed, ``bridge_mode`` its Bridge mode,
    ``bridge_stride`` its Bridge pixel stride when not the Bridge's own, ``init_args`` the
    initialiser's flags beyond its defaults)."""
    if "=" not in text:
        return text, {}
    name, cfg = text.split("=", 1)
    cfg = json.loads(cfg)
    if not isinstance(cfg, dict) or "recipe" not in cfg:
        raise ValueError(f"variant {name!r}: JSON object with a 'recipe' key expected")
    return name, cfg


def _check_selection(args, of_role, scenes) -> None:
    """Refuse a grid selection that names what the protocol does not hold (``--scenes`` not of
    the role, ``--n`` no selected scene has) or that selects nothing: a misspelt name is an
    error, never "0 runs to do".

    Raises:
        ValueError: one line naming the unknown values and the known ones.
    """
    known = [s.name for s in of_role]
    if args.scenes is not None:
        unknown = [n for n in args.scenes if n not in known]
        if unknown or not args.scenes:
            raise ValueError(f"--scenes {' '.join(unknown) if unknown else '(none given)'}: no such scene of role "
                             f"{args.role} in {args.protocol} (known: {', '.join(known) or 'none'})")
    if args.n is not None:
        views = sorted({n for s in scenes for n in s.views})
        unknown = [n for n in args.n if n not in views]
        if unknown or not args.n:
            raise ValueError(f"--n {' '.join(map(str, unknown)) if unknown else '(none given)'}: no selected scene "
                             f"has that view count (known: {', '.join(map(str, views)) or 'none'})")
    if not scenes:
        raise ValueError(f"no scene of role {args.role} in {args.protocol}: the grid is empty")


def check_folders(args) -> None:
    """The runner's folder rule, for every subcommand: ``--records`` and ``--work`` are folders
    (or do not exist yet, and are made), and ``--work`` (cells and trained models, never
    committed) does not lie inside the repository unless git ignores it there (``work/``).
    ValueError naming the folder and what to do otherwise; nothing is written."""
    import subprocess

    for flag, path in (("--records", args.records), ("--work", getattr(args, "work", None))):
        if path is not None and path.exists() and not path.is_dir():
            raise ValueError(f"{flag} {path} is not a folder: name a folder (it is made if missing)")
    work = getattr(args, "work", None)
    if work is None or not work.resolve().is_relative_to(REPO):
        return
    try:  # 0: ignored, 1: not ignored, 128: not a git checkout (no repository to keep clean)
        rc = subprocess.run(["git", "-C", str(REPO), "check-ignore", "-q", str(work.resolve())],
                            capture_output=True).returncode
    except OSError:  # no git here
        rc = 128
    if rc == 1:
        raise ValueError(f"--work {work} lies inside the repository, where git would list its cells and models "
                         f"as new files: pass a folder outside {REPO}, or under its ignored work/")


def cmd_run(args) -> int:
    from experiments.sparse_views.cells import prepare
    from experiments.sparse_views.runs import record, resolved_values, run_lock, run_name, stale_keys, train_and_score
    from runtime.atomic import atomic_path

    of_role = [s for s in protocol.load(args.protocol, args.data) if s.role == args.role]
    scenes = [s for s in of_role if args.scenes is None or s.name in args.scenes]
    _check_selection(args, of_role, scenes)
    # each variant once: its name, config, recipe, config overrides and the values its runs resolve
    plans = []
    from experiments.sparse_views.cells import seed_folder

    for name, cfg in (_variant(v) for v in args.recipes):
        # a bad seed choice fails here, before any run
        seed_folder(cfg.get("init", "posed"), cfg.get("bridge_mode"), cfg.get("bridge_stride"), cfg.get("init_args"))
        recipe = cfg.get("recipe", name)
        overrides = {k: v for k, v in cfg.items() if k != "recipe" and k not in SEED_KEYS}
        plans.append((name, cfg, recipe, overrides, resolved_values(recipe, overrides, args.iterations)))
    runs_dir = args.records / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    todo = []
    index, shard = -1, None
    if args.shard:
        try:
            shard = tuple(int(x) for x in args.shard.split("/"))
            if len(shard) != 2 or not 0 <= shard[0] < shard[1]:
                raise ValueError
        except ValueError:
            print(f"error: --shard must be K/M with 0 <= K < M, got {args.shard!r}", file=sys.stderr)
            return 2
    for s in scenes:
        if not s.available:
            print(f"SKIP {s.name}: {s.path} is not here (experiments/sparse_views/fetch_scenes.py fetches it)",
                  flush=True)
            continue
        # the scene's own background (scenes.yaml), the same for every recipe; it also stands
        # for a variant's "mean"
        bg = {} if s.background is None else {"background": list(s.background)}
        scene_plans = [(name, {**cfg, **bg}, recipe, {**overrides, **bg},
                        resolved_values(recipe, {**overrides, **bg}, args.iterations) if bg else want)
                       for name, cfg, recipe, overrides, want in plans]
        for n in s.views if args.n is None else [n for n in args.n if n in s.views]:
            for seed in args.seeds:  # seed-major: an interrupted grid holds whole seeds
                for name, cfg, recipe, overrides, want in scene_plans:
                    rec_path = runs_dir / f"{run_name(s.name, n, name, seed, args.iterations)}.json"
                    index += 1  # the run's place in the requested grid, recorded or not
                    if shard is not None and index % shard[1] != shard[0]:
                        continue
                    if not rec_path.is_file():
                        todo.append((s, n, seed, name, cfg, recipe, overrides, rec_path))
                        continue
                    kept = json.loads(rec_path.read_text()).get("values")
                    bad = ["values (an older record)"] if kept is None else stale_keys(kept, want)
                    if bad:
                        print(f"error: {rec_path} was made with other values of {', '.join(bad)} than "
                              f"{name!r} gives now: remove it (and its run folder under --work) to run it "
                              f"again", file=sys.stderr)
                        return 2
    print(f"{len(todo)} runs to do ({args.role}, {args.iterations} iterations)", flush=True)
    t0 = time.perf_counter()
    for i, (s, n, seed, name, cfg, recipe, overrides, rec_path) in enumerate(todo, 1):
        out = args.work / f"{s.name}_n{n}" / "runs" / run_name(s.name, n, name, seed, args.iterations)
        lock = out.with_name(out.name + ".lock")
        with run_lock(lock) as mine:
            # another run command over an overlapping grid: never the same run twice at once
            if not mine or rec_path.is_file():
                print(f"[{i}/{len(todo)}] {s.name} n={n} {name} seed {seed}: "
                      + ("recorded meanwhile" if mine else f"running in another process ({lock})") + ", skipped",
                      flush=True)
                continue
            started = datetime.now(timezone.utc).isoformat(timespec="seconds")  # the registration check's clock
            cell = prepare(args.work / f"{s.name}_n{n}", s, n, cfg.get("init", "posed"), cfg.get("bridge_mode"),
                           cfg.get("bridge_stride"), cfg.get("init_args"))
            res = train_and_score(cell, out, recipe, seed, args.iterations,
                                  args.eval_every or max(1, args.iterations // 10), overrides, args.kernel_threads)
            rec = record(s.name, s.role, n, name, seed, args.iterations, res, cfg or None)
            rec["background"] = res["background"]  # the colour it trained and rendered against ("mean" resolved)
            rec["load_avg"] = os.getloadavg()
            rec["started_at"] = started
            with atomic_path(rec_path) as tmp:  # a record is whole or absent
                tmp.write_text(json.dumps(rec, indent=1) + "\n")
        print(f"[{i}/{len(todo)} {time.perf_counter() - t0:6.0f} s] {s.name} n={n} {name} seed {seed}: "
              f"PSNR {rec['psnr']:.2f} SSIM {rec['ssim']:.3f} LPIPS-alex {rec['lpips_alex']:.3f} "
              f"vgg {rec['lpips_vgg']:.3f}, {rec['gaussians']} Gaussians, {rec['train_s']:.0f} s", flush=True)
    return 0


def cmd_summary(args) -> int:
    from experiments.sparse_views.summary import write_summary

    write_summary(args.records, args.doc, protocol.load(args.protocol, args.data), args.protocol)
    return 0


def cmd_floor(args) -> int:
    from experiments.sparse_views.floor import measure_floors

    scenes = [s for s in protocol.load(args.protocol, args.data) if s.role == args.role
              and (not args.scenes or s.name in args.scenes)]
    unknown = sorted(set(args.scenes or ()) - {s.name for s in scenes})
    if unknown:
        raise ValueError(f"no {args.role} scene named {', '.join(unknown)}")
    missing = [s.name for s in scenes if not s.generate and not s.available]
    if missing:
        raise FileNotFoundError(f"no data here for {', '.join(missing)} (pass --data DIR)")
    measure_floors(args.records, args.work, scenes, args.n)
    return 0


def cmd_relabel(args) -> int:
    from experiments.sparse_views.relabel import relabel

    moved = relabel(args.records / "runs", args.old, args.new, protocol.load(args.protocol, args.data),
                    args.stale_only, args.work, args.built_on)
    renamed = sum(a != b for a, b in moved)
    print(f"{renamed} records of {args.old!r} are now {args.new!r}"
          + (f", {len(moved) - renamed} records built on it now build on {args.new!r}" if args.built_on else "")
          + (f" (and their run folders under {args.work})" if args.work else ""))
    return 0


def cmd_reconfig(args) -> int:
    from experiments.sparse_views.relabel import reconfig

    try:
        config = json.loads(args.config)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--config {args.config!r} is not JSON ({exc.msg}): pass an object such as "
                         f"'{{\"recipe\": \"sparse\", \"background\": [0, 0, 0]}}'") from None
    done = reconfig(args.records / "runs", args.name, config, protocol.load(args.protocol, args.data))
    changed = sum(c for _, c, _ in done)
    print(f"{changed} of {len(done)} records of {args.name!r} now have config {json.dumps(config)}"
          f" ({sum(o for *_, o in done)} with their scene's own background; {len(done) - changed} had it already)")
    return 0


def cmd_list(args) -> int:
    for s in protocol.load(args.protocol, args.data):
        where = "generated" if s.path is None else (str(s.path) if s.available else f"missing: {s.path}")
        print(f"{s.name:24s} {s.role:10s} {s.kind:28s} n={list(s.views)}  {where}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from runtime.cliargs import plain

    p = argparse.ArgumentParser(prog="python -m experiments.sparse_views", description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--protocol", type=Path, default=protocol.PROTOCOL, help="the scenes file (default %(default)s)")
    p.add_argument("--data", type=Path, default=None,
                   help=f"folder of the real scenes (default ${protocol.DATA_ENV}, else the protocol's data_root)")
    p.add_argument("--records", type=Path, default=RECORDS, help="records folder (default %(default)s)")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="train and score the runs of one role that have no record")
    r.add_argument("--role", choices=protocol.RUN_ROLES, required=True,
                   help="the scenes to run (reserve scenes are never run: they wait for the next change of values)")
    r.add_argument("--scenes", nargs="*", default=None, help="only these scenes (default: every one of the role)")
    r.add_argument("--n", nargs="*", type=int, default=None, help="only these view counts")
    r.add_argument("--recipes", nargs="+", default=list(DEFAULT_RECIPES),
                   help="recipes, or tuning variants NAME='{\"recipe\": ..., key: value}' (default %(default)s); "
                        "a variant's \"background\": \"mean\" trains and renders against the mean colour of "
                        "the cell's training images (the trainer's; a scene's own background in scenes.yaml "
                        "stands instead); \"init\": posed (default), mvs or random seeds the cell from that "
                        "initialiser, \"bridge_mode\" its Bridge mode and \"bridge_stride\" its Bridge pixel "
                        "stride (mvs; default the Bridge's own), \"init_args\" its flags ({\"fill_stride\": 0})")
    r.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    r.add_argument("--iterations", type=int, default=1000)
    r.add_argument("--eval-every", type=int, default=None, help="held-out curve period (default iterations / 10)")
    r.add_argument("--work", type=Path, required=True, help="cells and trained models (not committed)")
    r.add_argument("--kernel-threads", type=int, default=1,
                   help="C++ kernel threads per run (default %(default)s: run two shards side by side)")
    r.add_argument("--shard", default=None,
                   help="K/M: of the requested grid's runs (recorded or not), every M-th from the K-th "
                        "(0-based), so that shards started at different times never share or skip a run")
    s = sub.add_parser("summary", help="rebuild summary.json and the docs table from the records")
    s.add_argument("--doc", type=Path, default=DOC, help="markdown table to write (default %(default)s)")
    sub.add_parser("list", help="the protocol's scenes")
    fl = sub.add_parser("floor", help="score a flat image of the training views' mean colour per cell")
    fl.add_argument("--role", choices=protocol.RUN_ROLES, default="evaluation", help="(default %(default)s)")
    fl.add_argument("--scenes", nargs="*", default=None, help="only these scenes (default: every one of the role)")
    fl.add_argument("--n", nargs="*", type=int, default=None, help="only these view counts (default: the scene's)")
    fl.add_argument("--work", type=Path, required=True, help="where the cells' scenes and splits are made")
    rl = sub.add_parser("relabel", help="rename the records of OLD to NEW (a value landed: the recipe's old "
                                        "runs become a variant, the candidate's the recipe's)")
    rl.add_argument("old", help="the records' name now (a recipe or a variant)")
    rl.add_argument("new", help="their new name; a recipe's or a kept variant's (splat_train.recipes.VARIANTS) only "
                                    "for records trained with what it gives now")
    rl.add_argument("--stale-only", action="store_true",
                    help="move only the records that OLD (a recipe) no longer resolves to")
    rl.add_argument("--work", type=Path, default=None, help="the run command's --work: rename the run folders too")
    rl.add_argument("--built-on", action="store_true",
                    help="also the records of variants built on OLD (config {\"recipe\": OLD, ...}): their config "
                         "names NEW, checked against NEW with their own keys")
    rc = sub.add_parser("reconfig", help="set the config of the records named NAME to JSON (what a run of their "
                                         "values is asked now), if every record's values are what JSON gives")
    rc.add_argument("name", help="the records' name (kept)")
    rc.add_argument("--config", required=True,
                    help="JSON object {\"recipe\": RECIPE, key: value, ...} (a recipe or a kept variant, "
                         "splat_train.recipes.VARIANTS, plus config keys); the scene's own background in scenes.yaml "
                         "is added where it has one")
    args = p.parse_args(argv)
    try:
        check_folders(args)
        return {"run": cmd_run, "summary": cmd_summary, "list": cmd_list,
                "relabel": cmd_relabel, "reconfig": cmd_reconfig, "floor": cmd_floor}[args.command](args)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"error: python -m experiments.sparse_views {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    from runtime.stops import run_command

    # a stop signal (SLURM's SIGTERM, Ctrl-C, SIGHUP) ends the runner with one line and 128 + the
    # signal, after the stage command it was running has ended cleanly (experiments._proc)
    sys.exit(run_command(main))
