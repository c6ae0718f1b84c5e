"""Rename the records of one recipe or variant when a recipe's value changes.

When a tuning round's value lands, the recipe's old runs are kept under a variant name (its
records stay in the table, beside the new ones: ``sparse`` before the change becomes
``sparse-r13``) and the candidate's runs, trained with exactly the values the recipe now gives,
become the recipe's (``sparse-bgmean`` becomes ``sparse``). Both are checked against the
recipe as it is now (:func:`experiments.sparse_views.runs.resolved_values`, with the scene's
own background from scenes.yaml), so that a record never carries a name whose values it
was not trained with:

- to a recipe name, or to a kept variant's (:data:`splat_train.recipes.VARIANTS`, a recipe's
  earlier values under a name of their own): every record moved must resolve to what the name
  gives now, or nothing moves; its ``config`` becomes what a run of it writes: ``{"recipe":
  NAME}``, with the scene's own ``background`` where scenes.yaml gives one. A record made
  before records kept their values (no ``values``) is checked on the schedule it keeps, and
  only a variant takes it: a recipe name needs every value;
- ``stale_only``: only the records that the recipe no longer matches move (a scene whose own
  background stood in for the changed value keeps its records under the recipe's name).

Every target name must be free (records and, with ``work``, run folders), or nothing moves.

``built_on``: the records of variants that build on ``old`` (another record name, a config
``{"recipe": OLD, ...}``: ``paper-mvs`` as ``{"recipe": "paper", "init": "mvs"}``) keep their
name, and their config's recipe becomes ``new``, checked the same way with the variant's own
config keys (its seed keys aside). The same check serves the records of other layouts
(:func:`matches`: the recipe study's runs, which keep only their schedule).

:func:`reconfig` keeps the name and sets the config alone: a variant's records whose values a
recipe's own name no longer gives, but the recipe with a key set (or a kept variant with a key its
records predate) does (``sparse-r13``: ``{"recipe": "sparse", "background": [0, 0, 0]}``) say
so, checked the same way, every record or none.
"""

from __future__ import annotations

import json
from pathlib import Path

from experiments.sparse_views.runs import SEED_KEYS, resolved_values, run_name, stale_keys


def overrides(config: dict | None) -> dict:
    """A record's config keys that set training values: all but its ``recipe`` and seed keys."""
    return {k: v for k, v in (config or {}).items() if k != "recipe" and k not in SEED_KEYS}


def matches(values: dict | None, schedule: dict | None, recipe: str, config: dict, iterations: int,
            schedule_only: bool = False) -> bool:
    """Whether a run's kept ``values`` are what ``recipe`` (a recipe or a variant) with the config
    keys ``config`` resolves to now at ``iterations``; ``schedule_only``: a run without ``values``
    is judged on its ``schedule`` (iterations; its ``source`` aside), else it matches nothing."""
    want = resolved_values(recipe, config, iterations)
    found = values
    if found is None:
        if not schedule_only or not schedule:
            return False
        found = {k: v for k, v in schedule.items() if k != "source"}
        want = {k: want[k] for k in found}
    return stale_keys(found, want) == []


def _current(rec: dict, recipe: str, backgrounds: dict, schedule_only: bool = False, own: bool = False) -> bool:
    """Whether the record's values are what ``recipe`` (a recipe or a variant) resolves to now on
    its scene (:func:`matches`); ``own``: with its config's own keys (a variant built on it)."""
    bg = backgrounds.get(rec["scene"])
    cfg = {**(overrides(rec.get("config")) if own else {}), **({} if bg is None else {"background": list(bg)})}
    return matches(rec.get("values"), rec.get("schedule"), recipe, cfg, rec["iterations"], schedule_only)


def relabel(runs_dir: Path, old: str, new: str, scenes: list, stale_only: bool = False,
            work: Path | None = None, built_on: bool = False) -> list[tuple[Path, Path]]:
    """Rename the records named ``old`` to ``new`` (file name and ``recipe``), and with
    ``work`` their run folders (``WORK/<scene>_n<n>/runs/<run name>``); with ``built_on``, give
    the records of variants built on ``old`` the config recipe ``new`` (module docstring).

    Args:
        runs_dir: the records' folder (``experiments/records/sparse_views/runs``).
        old, new: the record names (a recipe or a variant).
        scenes: the protocol's scenes (:func:`protocol.load`), for their backgrounds.
        stale_only: move only the records that ``old`` (a recipe) no longer resolves to.
        work: the benchmark's --work folder, whose run folders move with their records.
        built_on: also the records of other names whose config's recipe is ``old``.

    Returns:
        The (old, new) record paths moved (the same path twice for a record whose config
        alone changed).

    Raises:
        ValueError: a record moved to a recipe name does not match the recipe now, a target
            name is taken, or nothing is named ``old``.
    """
    from runtime.atomic import atomic_path
    from splat_train.recipes import RECIPE_NAMES, VARIANTS

    if old == new:
        raise ValueError("relabel: the old and the new name are the same")
    if stale_only and old not in RECIPE_NAMES:
        raise ValueError(f"relabel --stale-only: {old!r} is not a recipe, so no record of it can be stale")
    backgrounds = {s.name: s.background for s in scenes}
    found = []
    for path in sorted(Path(runs_dir).glob("*.json")):
        rec = json.loads(path.read_text())
        if rec.get("recipe") == old or (built_on and (rec.get("config") or {}).get("recipe") == old):
            found.append((path, rec))
    if not found:
        raise ValueError(f"relabel: no record in {runs_dir} is named {old!r}"
                         + (" or builds on it" if built_on else ""))
    if stale_only:
        found = [(p, r) for p, r in found if not _current(r, old, backgrounds, own=r["recipe"] != old)]
    named = new in RECIPE_NAMES or new in VARIANTS  # a name whose values a record must have
    if named:
        kind = "recipe" if new in RECIPE_NAMES else "variant"
        bad = [p.name for p, r in found
               if not _current(r, new, backgrounds, schedule_only=kind == "variant", own=r["recipe"] != old)]
        if bad:
            raise ValueError(f"relabel: {len(bad)} record(s) of {old!r} were not trained with what {kind} "
                             f"{new!r} gives now (e.g. {bad[0]}); nothing moved")
    moves = []
    if built_on and not named:
        raise ValueError(f"relabel --built-on: {new!r} is neither a recipe nor a kept variant, so no config can "
                         f"name it")
    for path, rec in found:
        if rec["recipe"] != old:  # a variant built on old: its config alone changes
            moves.append((path, rec, path, None))
            continue
        a = run_name(rec["scene"], rec["n"], old, rec["seed"], rec["iterations"])
        b = run_name(rec["scene"], rec["n"], new, rec["seed"], rec["iterations"])
        target, folders = path.with_name(f"{b}.json"), None
        if work is not None:
            cell = Path(work) / f"{rec['scene']}_n{rec['n']}" / "runs"
            folders = (cell / a, cell / b)
        for taken in (target, folders[1]) if folders else (target,):
            if taken.exists():
                raise ValueError(f"relabel: {taken} exists already; nothing moved")
        moves.append((path, rec, target, folders))
    for path, rec, target, folders in moves:
        renamed = rec["recipe"] == old
        rec = {**rec, "recipe": new if renamed else rec["recipe"]}
        if named:  # as cmd_run writes a run of the recipe or variant on this scene (a variant keeps its keys)
            bg = backgrounds.get(rec["scene"])
            cfg = rec.get("config") or {}
            keep = {k: v for k, v in cfg.items() if k in SEED_KEYS} if renamed else cfg
            rec["config"] = {**keep, "recipe": new, **({} if bg is None else {"background": list(bg)})}
        with atomic_path(target) as tmp:
            tmp.write_text(json.dumps(rec, indent=1) + "\n")
        if target != path:
            path.unlink()
        if folders is not None and folders[0].is_dir():
            folders[0].rename(folders[1])
    return [(m[0], m[2]) for m in moves]


def reconfig(runs_dir: Path, name: str, config: dict, scenes: list) -> list[tuple[Path, bool, bool]]:
    """Set the ``config`` of every record filed under ``name`` to ``config`` (with the scene's
    own background from scenes.yaml where it has one, as a run writes it), only if each record's
    kept values are what that config resolves to now (:func:`matches`; a record without
    ``values`` only on its schedule, and only for a kept variant with no other keys).

    A record's seed keys (:data:`SEED_KEYS`) are not values: ``config`` keeps the record's where it
    names none, and one that names others than a record's is a mismatch.

    Args:
        runs_dir: the records' folder (``experiments/records/sparse_views/runs``).
        name: the records' name (their ``recipe``), kept.
        config: what a run of them is asked: ``{"recipe": RECIPE, key: value, ...}``.
        scenes: the protocol's scenes (:func:`protocol.load`), for their backgrounds.

    Returns:
        Per record of ``name``: its path, whether its config changed (a record that has the
        config already is left as it is) and whether it took its scene's background.

    Raises:
        ValueError: ``config`` is not an object with a known ``recipe``, nothing is named
            ``name``, or a record's values are not what ``config`` gives now; nothing is written.
    """
    from runtime.atomic import atomic_path
    from splat_train.recipes import VARIANTS

    if not isinstance(config, dict) or not isinstance(config.get("recipe"), str):
        raise ValueError(f"reconfig: --config must be a JSON object with a \"recipe\", got {json.dumps(config)}")
    backgrounds = {s.name: s.background for s in scenes}
    found = [(p, r) for p, r in ((p, json.loads(p.read_text())) for p in sorted(Path(runs_dir).glob("*.json")))
             if r.get("recipe") == name]
    if not found:
        raise ValueError(f"reconfig: no record in {runs_dir} is named {name!r}")
    asked_seed = {k: v for k, v in config.items() if k in SEED_KEYS}
    schedule_only = config["recipe"] in VARIANTS and not overrides(config)
    plans, bad = [], []
    for path, rec in found:
        bg = backgrounds.get(rec["scene"])
        own_seed = {k: v for k, v in (rec.get("config") or {}).items() if k in SEED_KEYS}
        cfg = {"recipe": config["recipe"], **(asked_seed or own_seed), **overrides(config),
               **({} if bg is None else {"background": list(bg)})}
        same_seed = not asked_seed or asked_seed == own_seed
        if not same_seed or not matches(rec.get("values"), rec.get("schedule"), cfg["recipe"], overrides(cfg),
                                        rec["iterations"], schedule_only):
            bad.append(path.name)
        plans.append((path, rec, cfg, bg is not None))
    if bad:
        raise ValueError(f"reconfig: {len(bad)} of {len(found)} record(s) of {name!r} were not trained with what "
                         f"{json.dumps(config)} gives now (e.g. {bad[0]}); nothing written")
    done = []
    for path, rec, cfg, own in plans:
        changed = rec.get("config") != cfg
        if changed:
            with atomic_path(path) as tmp:
                tmp.write_text(json.dumps({**rec, "config": cfg}, indent=1) + "\n")
        done.append((path, changed, own))
    return done
