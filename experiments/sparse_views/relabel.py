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
"""

from __future__ import annotations

import json
from pathlib import Path

from experiments.sparse_views.runs import resolved_values, run_name, stale_keys


def _current(rec: dict, recipe: str, backgrounds: dict, schedule_only: bool = False) -> bool:
    """Whether the record's values are what ``recipe`` (a recipe or a variant) resolves to now on
    its scene; ``schedule_only``: a record without ``values`` is judged on its ``schedule``."""
    bg = backgrounds.get(rec["scene"])
    want = resolved_values(recipe, {} if bg is None else {"background": list(bg)}, rec["iterations"])
    found = rec.get("values")
    if found is None:
        if not schedule_only or not rec.get("schedule"):
            return False
        found = {k: v for k, v in rec["schedule"].items() if k != "source"}
        want = {k: want[k] for k in found}
    return stale_keys(found, want) == []


def relabel(runs_dir: Path, old: str, new: str, scenes: list, stale_only: bool = False,
            work: Path | None = None) -> list[tuple[Path, Path]]:
    """Rename the records named ``old`` to ``new`` (file name and ``recipe``), and with
    ``work`` their run folders (``WORK/<scene>_n<n>/runs/<run name>``).

    Args:
        runs_dir: the records' folder (``experiments/records/sparse_views/runs``).
        old, new: the record names (a recipe or a variant).
        scenes: the protocol's scenes (:func:`protocol.load`), for their backgrounds.
        stale_only: move only the records that ``old`` (a recipe) no longer resolves to.
        work: the benchmark's --work folder, whose run folders move with their records.

    Returns:
        The (old, new) record paths moved.

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
        if rec.get("recipe") == old:
            found.append((path, rec))
    if not found:
        raise ValueError(f"relabel: no record in {runs_dir} is named {old!r}")
    if stale_only:
        found = [(p, r) for p, r in found if not _current(r, old, backgrounds)]
    named = new in RECIPE_NAMES or new in VARIANTS  # a name whose values a record must have
    if named:
        kind = "recipe" if new in RECIPE_NAMES else "variant"
        bad = [p.name for p, r in found if not _current(r, new, backgrounds, schedule_only=kind == "variant")]
        if bad:
            raise ValueError(f"relabel: {len(bad)} record(s) of {old!r} were not trained with what {kind} "
                             f"{new!r} gives now (e.g. {bad[0]}); nothing moved")
    moves = []
    for path, rec in found:
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
        rec = {**rec, "recipe": new}
        if named:  # as cmd_run writes a run of the recipe or variant on this scene
            bg = backgrounds.get(rec["scene"])
            rec["config"] = {"recipe": new, **({} if bg is None else {"background": list(bg)})}
        with atomic_path(target) as tmp:
            tmp.write_text(json.dumps(rec, indent=1) + "\n")
        path.unlink()
        if folders is not None and folders[0].is_dir():
            folders[0].rename(folders[1])
    return [(m[0], m[2]) for m in moves]
