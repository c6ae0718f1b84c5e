"""A pre-registered comparison of seeds (initialisers) under one recipe, from the records.

    python -m experiments.sparse_views.seeds command [--registration FILE] [--work DIR]
    python -m experiments.sparse_views.seeds report  [--registration FILE] [--work DIR] [--doc FILE]

The registration (``registered/*.yaml``, committed before any of its runs) fixes the scenes,
view count, seeds, budget, variants and targets. ``command`` prints the ``python -m
experiments.sparse_views run`` line that makes its records; ``report`` reads them and writes
``<records>/<name>.json`` (the registration's own ``records`` folder, else
``experiments/records/sparse_views``) and a markdown page: per scene and variant the
final held-out PSNR, SSIM, LPIPS, the coverage of the held-out pixels and the PSNR over the
covered ones (alpha >= 0.5: splat_train/training/heldout.py); the floor, a flat image of the training
views' mean colour scored like a model (from the cells under ``--work``); per comparison the
per-scene difference (paired by seed, then the mean over seeds), its mean over the scenes with a
95 % t interval taking the scene as the unit, how many scenes are ahead, and the verdict of
each registered target. A registration whose runs are incomplete is reported as such. The JSON's
``registration`` block and one sentence of the page say whether the registration's commit came
before every run (:mod:`experiments.sparse_views.provenance`; a run made before it is named).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections import defaultdict
from pathlib import Path

from experiments.sparse_views.floor import floor_psnr, load_floors
from experiments.sparse_views.scene_level import interval as _interval
from experiments.sparse_views.protocol import REPO

HERE = Path(__file__).resolve().parent
RECORDS = REPO / "experiments" / "records" / "sparse_views"
DEFAULT_REGISTRATION = HERE / "registered" / "mvs_seed.yaml"
MEASURES = ("psnr", "ssim", "lpips_alex", "lpips_vgg")
#: a target's ``than`` may name the floor: a flat image of the training views' mean colour
FLOOR = "floor"
#: a target's conditions beside its mean PSNR difference ``by``: the 95 % interval's low end
#: above 0, and an LPIPS (Alex) difference at or below 0
TARGET_CONDITIONS = ("interval_above_zero", "lpips_no_worse")

__all__ = ["load_registration", "run_command", "floor_psnr", "report", "markdown"]


def load_registration(path: Path) -> dict:
    """The registration, checked: scenes, n, seeds, iterations, variants (each with a recipe),
    targets naming known variants."""
    import yaml

    reg = yaml.safe_load(Path(path).read_text())
    for key in ("name", "role", "scenes", "n", "seeds", "iterations", "variants"):
        if key not in reg:
            raise ValueError(f"{path}: no {key!r}")
    rec = reg.get("records")
    if rec is not None and (not isinstance(rec, str) or Path(rec).is_absolute() or ".." in Path(rec).parts):
        raise ValueError(f"{path}: 'records' is a folder inside the repository, relative to it; got {rec!r}")
    for name, v in reg["variants"].items():
        if not isinstance(v, dict) or "recipe" not in v:
            raise ValueError(f"{path}: variant {name!r} needs a recipe")
    for t in reg.get("targets", []) + reg.get("measured_without_target", []):
        for side in ("better", "than"):
            if t[side] not in reg["variants"] and not (side == "than" and t[side] == FLOOR):
                raise ValueError(f"{path}: {t[side]!r} is not a variant" + (f" (or {FLOOR!r})" if side == "than" else ""))
        unknown = set(t) - {"better", "than", "by", *TARGET_CONDITIONS}
        if unknown:
            raise ValueError(f"{path}: unknown target keys {sorted(unknown)} (known: better, than, by, "
                             f"{', '.join(TARGET_CONDITIONS)})")
    return reg


#: the pre-registered sets: each on scenes no earlier set measured (tests/test_sparse_views_scenes.py)
REGISTERED = HERE / "registered"
#: comparisons whose values were fixed before their runs, on scenes a registration measured before
REMEASURED = HERE / "remeasured"


def measured_before(reg: dict, path: Path | None) -> dict[str, list[str]]:
    """{registration name: the scenes it shares with ``reg``} over the pre-registered sets
    (:data:`REGISTERED`) other than ``path``: a comparison on such scenes is not one on unseen
    scenes, whatever it fixed before its runs."""
    out = {}
    for other in sorted(REGISTERED.glob("*.yaml")):
        if path is not None and other.resolve() == Path(path).resolve():
            continue
        shared = sorted(set(reg["scenes"]) & set(load_registration(other)["scenes"]))
        if shared:
            out[other.stem] = shared
    return out


def measured_sentence(before: dict[str, list[str]], scenes: int) -> str:
    """One sentence naming the pre-registered sets that measured these scenes before."""
    sets = "; ".join(f"`{name}` measured {len(sc)} of the {scenes}" for name, sc in before.items())
    return (f"Not an evaluation on unseen scenes: {sets} before, so these figures are not pre-registered "
            "results, only comparisons whose values were fixed before their runs.")


def target_met(c: dict, complete: bool) -> bool:
    """A registered target's verdict: every scene measured, the mean PSNR difference at least
    ``by``, and each of its conditions (:data:`TARGET_CONDITIONS`) held."""
    iv, lp = c["psnr_diff"], c["lpips_alex_diff"]
    if not complete or iv is None or iv["mean"] is None or iv["mean"] < c["by"]:
        return False
    if "interval_above_zero" in c.get("conditions", ()) and (iv["lo"] is None or iv["lo"] <= 0):
        return False
    if "lpips_no_worse" in c.get("conditions", ()) and (lp is None or lp["mean"] > 0):
        return False
    return True


def records_dir(reg: dict) -> Path:
    """Where the registration's records live: its own ``records`` folder (relative to the
    repository), else the benchmark's."""
    return REPO / reg["records"] if reg.get("records") else RECORDS


def as_recorded(reg: dict, records: Path) -> dict:
    """The registration as its records hold it: a registered recipe whose runs were trained
    before it took other values, and so were kept under a variant (``paper`` as ``paper-seedcode``,
    :data:`splat_train.recipes.VARIANTS`, by ``python -m experiments.sparse_views relabel``), is
    that variant in the variants (its record name and every config's recipe) and targets; the
    map is ``kept`` ({registered recipe: variant}). Read from the records' own configs, so a
    registration whose records name the recipe stays as registered."""
    from splat_train.recipes import VARIANTS

    kept = {}
    for name, v in reg["variants"].items():
        names = [name] + [k for k in VARIANTS if name == v["recipe"]]  # a recipe's own runs may carry a variant's name
        for cand in names:
            hits = sorted((records / "runs").glob(f"*_n{reg['n']}_{cand}_s*_i{reg['iterations']}.json"))
            found = {(json.loads(p.read_text()).get("config") or {}).get("recipe") for p in hits}
            if found and found <= set(VARIANTS) and len(found) == 1 and v["recipe"] not in found:
                kept[v["recipe"]] = found.pop()
                break
    if not kept:
        return {**reg, "kept": {}}
    def rename(name):
        return kept.get(name, name) if name in reg["variants"] and reg["variants"][name] == {"recipe": name} else name
    variants = {rename(n): {**v, "recipe": kept.get(v["recipe"], v["recipe"])} for n, v in reg["variants"].items()}
    side = lambda items: [{**t, "better": rename(t["better"]), "than": rename(t["than"])} for t in items]  # noqa: E731
    return {**reg, "variants": variants, "targets": side(reg.get("targets", [])),
            "measured_without_target": side(reg.get("measured_without_target", [])), "kept": kept}


def kept_sentence(kept: dict) -> str:
    """One sentence naming each registered recipe that its records hold as a kept variant."""
    if not kept:
        return ""
    return " ".join(f"`{r}` in that registration is the variant `{v}` (trained before `{r}` took its release's "
                    f"values)." for r, v in kept.items())


def run_command(reg: dict, work: str = "WORK") -> str:
    """The run line that makes the registration's records (one shard; ``--shard K/2`` splits it)."""
    variants = []
    for name, v in reg["variants"].items():
        variants.append(name if v == {"recipe": name} else f"{name}={json.dumps(v, separators=(',', ':'))}")
    records = ["--records", reg["records"]] if reg.get("records") else []
    args = ["python", "-m", "experiments.sparse_views", *records, "run", "--role", reg["role"], "--scenes", *reg["scenes"],
            "--n", str(reg["n"]), "--seeds", *map(str, reg["seeds"]), "--iterations", str(reg["iterations"]),
            "--work", work, "--recipes", *variants]
    return shlex.join(args)


def run_files(reg: dict, records: Path) -> dict[tuple[str, str, int], Path]:
    """The registration's recorded runs: (variant, scene, seed) -> its record under ``records/runs``."""
    out = {}
    for name in reg["variants"]:
        for scene in reg["scenes"]:
            for seed in reg["seeds"]:
                p = records / "runs" / f"{scene}_n{reg['n']}_{name}_s{seed}_i{reg['iterations']}.json"
                if p.is_file():
                    out[(name, scene, seed)] = p
    return out


def report(reg: dict, records: Path, work: Path | None, registration: Path | None = None,
           shown: str | None = None) -> dict:
    """The figures of the registration (module docstring) from ``records/runs``; with the
    registration's file (``shown``: its name in the records), also its ``registration`` block:
    the commit that added it against the runs' times (:func:`experiments.sparse_views.provenance.check`)."""
    reg = as_recorded(reg, records)
    files = run_files(reg, records)
    runs = {k: json.loads(p.read_text()) for k, p in files.items()}
    expected = len(reg["variants"]) * len(reg["scenes"]) * len(reg["seeds"])
    per = defaultdict(dict)  # variant -> scene -> measures (means over seeds)
    for name in reg["variants"]:
        for scene in reg["scenes"]:
            rs = [runs[(name, scene, s)] for s in reg["seeds"] if (name, scene, s) in runs]
            if len(rs) != len(reg["seeds"]):
                continue
            row = {m: sum(r[m] for r in rs) / len(rs) for m in MEASURES}
            row["coverage"] = sum(r["curve"]["coverage"][-1] for r in rs) / len(rs)
            row["psnr_covered"] = sum(r["curve"]["psnr_covered"][-1] for r in rs) / len(rs)
            row["gaussians"] = sum(r["gaussians"] for r in rs) / len(rs)
            row["seed_gaussians"] = sum(r["seed_gaussians"] for r in rs) / len(rs)
            per[name][scene] = row
    complete = [s for s in reg["scenes"] if all(s in per[v] for v in reg["variants"])]
    # from the cells when they are here, else as `python -m experiments.sparse_views floor` recorded it
    recorded = load_floors(RECORDS)
    floor = {s: (floor_psnr(work / f"{s}_n{reg['n']}") if work else None) or recorded.get(s, {}).get(reg["n"])
             for s in reg["scenes"]}
    comparisons = []
    for kind, items in (("target", reg.get("targets", [])), ("measured", reg.get("measured_without_target", []))):
        for t in items:
            if t["than"] == FLOOR:
                base = [s for s in complete if floor.get(s) is not None]
                diffs = {s: per[t["better"]][s]["psnr"] - floor[s] for s in base}
                lp = {}
            else:
                diffs = {s: per[t["better"]][s]["psnr"] - per[t["than"]][s]["psnr"] for s in complete}
                lp = {s: per[t["better"]][s]["lpips_alex"] - per[t["than"]][s]["lpips_alex"] for s in complete}
            iv = _interval(list(diffs.values())) if diffs else None
            conditions = [k for k in TARGET_CONDITIONS if t.get(k)]
            c = {"kind": kind, "better": t["better"], "than": t["than"], "by": t.get("by"),
                 **({"conditions": conditions} if conditions else {}),
                 "psnr_diff_per_scene": diffs, "psnr_diff": iv,
                 "lpips_alex_diff": _interval(list(lp.values())) if lp else None,
                 "scenes_ahead": sum(d > 0 for d in diffs.values()), "scenes": len(diffs)}
            if kind == "target":
                c["met"] = target_met(c, complete=len(complete) == len(reg["scenes"]) == len(diffs))
            comparisons.append(c)
    out = {"name": reg["name"], "scenes": reg["scenes"], "n": reg["n"], "seeds": reg["seeds"],
            "iterations": reg["iterations"], "variants": reg["variants"], "runs": len(runs),
            "runs_expected": expected, "complete_scenes": complete, "floor_psnr": floor,
            "per_scene": {v: dict(per[v]) for v in reg["variants"]}, "comparisons": comparisons}
    if reg["kept"]:
        out["kept"] = reg["kept"]
    before = measured_before(reg, registration)
    if before:
        out["scenes_measured_before"] = before
    if registration is not None:
        from experiments.sparse_views.provenance import check

        out["registration"] = check(registration, list(files.values()), shown or str(registration))
    return out


def _f(x, fmt="{:.2f}") -> str:
    return "-" if x is None else fmt.format(x)


#: the line that marks a page ``report`` wrote: ``--doc FILE`` replaces only a file holding it
#: (experiments.sparse_views.summary.check_doc)
GENERATED = "Generated by `python -m experiments.sparse_views.seeds report`"


CONDITION_TEXT = {"interval_above_zero": "interval above 0", "lpips_no_worse": "LPIPS no worse"}


def target_text(c: dict, ge: str = ">=") -> str:
    """A comparison's target as the pages write it: the mean difference and its conditions."""
    if c["kind"] != "target":
        return "none (measured)"
    return ", ".join([f"{ge} +{c['by']:.1f} dB", *(CONDITION_TEXT[k] for k in c.get("conditions", []))])


def backgrounds(variants: dict) -> str:
    """One clause naming each variant's background: its own, else its recipe's."""
    from splat_train.recipes import BACKGROUND_BLACK, BACKGROUND_MEAN, recipe_defaults

    def bg(v: dict) -> str:
        b = v.get("background", recipe_defaults(v["recipe"]).get("background"))
        if b == BACKGROUND_MEAN:
            return "the training views' mean colour"
        return "black" if list(b) == list(BACKGROUND_BLACK) else f"RGB {list(b)}"

    kinds = {name: bg(v) for name, v in variants.items()}
    if set(kinds.values()) == {"black"}:
        return "every variant at the scene's one background (black)"
    return "background: " + ", ".join(f"`{n}` {k}" for n, k in kinds.items())


def markdown(rep: dict, registration: str, command: str) -> str:
    from experiments.sparse_views.provenance import sentence

    checked = (" " + sentence(rep["registration"], f"commit that added `{registration}`")
               if rep.get("registration") else "")
    lines = [f"# Seeds compared: {rep['name']}", "",
             f"{GENERATED} from the records of the registration `{registration}`.{checked} {rep['runs']} of "
             f"{rep['runs_expected']} runs recorded; n = {rep['n']}, seeds {rep['seeds']}, "
             f"{rep['iterations']} iterations on a CPU; {backgrounds(rep['variants'])}."
             + (" " + kept_sentence(rep["kept"]) if rep.get("kept") else "")
             + (" " + measured_sentence(rep["scenes_measured_before"], len(rep["scenes"]))
                if rep.get("scenes_measured_before") else ""), "",
             "Final held-out PSNR (dB) over the full image, and over the pixels the model covers "
             "(accumulated alpha >= 0.5) with the covered share; the floor is a flat image of the training "
             "views' mean colour, scored like a model. Means over seeds.", "",
             "| scene | floor | " + " | ".join(f"{v} PSNR / covered (share)" for v in rep["variants"]) + " |",
             "|---|---|" + "---|" * len(rep["variants"])]
    for s in rep["scenes"]:
        cells = []
        for v in rep["variants"]:
            r = rep["per_scene"][v].get(s)
            cells.append("-" if r is None else f"{r['psnr']:.2f} / {r['psnr_covered']:.2f} ({r['coverage']:.2f})")
        lines.append(f"| {s} | {_f(rep['floor_psnr'].get(s))} | " + " | ".join(cells) + " |")
    lines += ["", "| variant | scenes | PSNR | SSIM | LPIPS (Alex) | LPIPS (VGG) | seed Gaussians | Gaussians |",
              "|---|---|---|---|---|---|---|---|"]
    for v in rep["variants"]:
        rows = [rep["per_scene"][v][s] for s in rep["complete_scenes"] if s in rep["per_scene"][v]]
        if not rows:
            continue
        mean = {k: sum(r[k] for r in rows) / len(rows) for k in (*MEASURES, "seed_gaussians", "gaussians")}
        lines.append(f"| {v} | {len(rows)} | {mean['psnr']:.2f} | {mean['ssim']:.3f} | {mean['lpips_alex']:.3f} | "
                     f"{mean['lpips_vgg']:.3f} | {mean['seed_gaussians']:.0f} | {mean['gaussians']:.0f} |")
    floors = [rep["floor_psnr"][s] for s in rep["complete_scenes"] if rep["floor_psnr"].get(s) is not None]
    if floors:
        lines.append(f"| floor (flat mean colour) | {len(floors)} | {sum(floors) / len(floors):.2f} | | | | | |")
    lines += ["", "Differences in final PSNR, per scene the mean over seeds of the seed-paired difference; the "
              "interval is a 95 % t interval over the scenes (the scene is the unit).", "",
              "| comparison | mean (95 % interval) | scenes ahead | LPIPS (Alex) difference | target | verdict |",
              "|---|---|---|---|---|---|"]
    for c in rep["comparisons"]:
        iv, lp = c["psnr_diff"], c["lpips_alex_diff"]
        span = "-" if iv is None else f"{iv['mean']:+.2f} [{iv['lo']:+.2f}, {iv['hi']:+.2f}]"
        lps = "-" if lp is None else f"{lp['mean']:+.3f}"
        target = target_text(c)
        verdict = ("met" if c["met"] else "missed") if c["kind"] == "target" else "-"
        if c["kind"] == "target" and len(rep["complete_scenes"]) < len(rep["scenes"]):
            verdict = "incomplete"
        lines.append(f"| {c['better']} - {c['than']} | {span} | {c['scenes_ahead']}/{c['scenes']} | {lps} | "
                     f"{target} | {verdict} |")
    lines += ["", "Rerun (records are kept; a second call trains nothing that is recorded):", "",
              "```bash", command,
              f"python -m experiments.sparse_views.seeds report --registration {registration} --work WORK", "```", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.sparse_views.seeds", description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("command", "report"))
    p.add_argument("--registration", type=Path, default=DEFAULT_REGISTRATION, help="default %(default)s")
    p.add_argument("--records", type=Path, default=None,
                   help="default: the registration's own 'records' folder, else experiments/records/sparse_views")
    p.add_argument("--work", type=Path, default=None, help="the run command's --work (the cells: the floor)")
    p.add_argument("--doc", type=Path, default=None, help="markdown page (default docs/results-<name>.md)")
    args = p.parse_args(argv)
    try:
        reg = load_registration(args.registration)
    except (OSError, ValueError, KeyError) as exc:
        print(f"python -m experiments.sparse_views.seeds: {exc}", file=sys.stderr)
        return 2
    args.records = args.records or records_dir(reg)
    command = run_command(as_recorded(reg, args.records), str(args.work) if args.work else "WORK")
    if args.what == "command":
        print(command)
        return 0
    doc = args.doc or REPO / "docs" / f"results-{reg['name'].replace('_', '-')}.md"
    from experiments.sparse_views.summary import check_doc

    try:
        check_doc(doc, GENERATED)  # before anything is written: a page the user wrote is never replaced
    except ValueError as exc:
        print(f"python -m experiments.sparse_views.seeds: error: {exc}", file=sys.stderr)
        return 2
    rel = args.registration.resolve().relative_to(REPO) if args.registration.resolve().is_relative_to(REPO) \
        else args.registration
    rep = report(reg, args.records, args.work, args.registration, str(rel))
    from runtime.atomic import atomic_path, write_json

    write_json(args.records / f"{reg['name']}.json", rep)
    with atomic_path(doc) as tmp:
        tmp.write_text(markdown(rep, str(rel), run_command(as_recorded(reg, args.records))))
    for c in rep["comparisons"]:
        iv = c["psnr_diff"]
        print(f"{c['better']} - {c['than']}: " + ("no complete scene" if iv is None else
              f"{iv['mean']:+.2f} dB [{iv['lo']:+.2f}, {iv['hi']:+.2f}] over {iv['k']} scenes"))
    b = rep["registration"]
    print("registration: " + (b["reason"] if b.get("verifiable") is False else
          f"{b['runs_after']} runs after it, {len(b['runs_before'])} before, {len(b['runs_unplaced'])} unplaced"))
    print(f"{rep['runs']}/{rep['runs_expected']} runs; wrote {doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
