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
