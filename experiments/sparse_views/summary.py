"""The sparse-view table, rebuilt from the run records: summary.json and a markdown page.

Per (scene, n, recipe, iterations): mean and 95 % t half-width over seeds
(:func:`evaluation.study.stats.t_interval`) of the final PSNR, SSIM, LPIPS-Alex, LPIPS-VGG,
Gaussian count and training seconds. Per evaluation scene, ``sparse`` against every other
recipe paired by seed. The verdicts of the benchmark's targets are computed here from the
same numbers, never written by hand, with how the lead is spread over the scenes (by kind,
where ``sparse`` is best, each scene left out in turn). Whether each evaluation scene took its
role in a commit before every run on it: the ``registration`` block and a sentence of the page
(:mod:`experiments.sparse_views.provenance`).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

from experiments.sparse_views import scene_level
from experiments.sparse_views.floor import load_floors
from experiments.sparse_views.protocol import REPO
from experiments.sparse_views.runs import RECORD_KEYS
from runtime.atomic import atomic_path
from splat_train.recipes import RECIPE_NAMES

MEASURES = ("psnr", "ssim", "lpips_alex", "lpips_vgg", "gaussians", "train_s")
HEAD = {"psnr": "PSNR", "ssim": "SSIM", "lpips_alex": "LPIPS-Alex", "lpips_vgg": "LPIPS-VGG",
        "gaussians": "Gaussians", "train_s": "train s"}
OURS, BASE = "sparse", "paper"
MAX_GAUSSIANS = 60_000  # the size target of a sparse-view model
TARGET_N = 3  # the view count the targets are stated at; other counts get the same measures


def record_files(records: Path) -> list[tuple[Path, dict]]:
    """Every run record under ``records/runs`` with its file, checked for :data:`RECORD_KEYS`."""
    out = []
    for p in sorted((records / "runs").glob("*.json")):
        r = json.loads(p.read_text())
        missing = [k for k in RECORD_KEYS if k not in r]
        if missing:
            raise ValueError(f"{p}: record lacks {missing}")
        out.append((p, r))
    return out


def load_records(records: Path) -> list[dict]:
    return [r for _, r in record_files(records)]


def _interval(values) -> dict:
    from evaluation.study.stats import t_interval

    mean, hw, k = t_interval([v for v in values if v is not None])
    return {"mean": None if math.isnan(mean) else mean, "hw95": None if math.isnan(hw) else hw, "k": k}


def aggregate(rows: list[dict]) -> list[dict]:
    """One row per (role, scene, n, iterations, recipe), recipes in first-seen order."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["role"], r["scene"], r["n"], r["iterations"], r["recipe"])].append(r)
    out = []
    for (role, scene, n, its, recipe), rs in groups.items():
        row = {"role": role, "scene": scene, "n": n, "iterations": its, "recipe": recipe,
               "seeds": sorted(r["seed"] for r in rs), "backend": sorted({str(r["backend"]) for r in rs})}
        for m in MEASURES:
            row[m] = _interval([r[m] for r in rs])
        row["best_psnr"] = _interval([r.get("best_psnr") for r in rs])
        out.append(row)
    return out


def paired(rows: list[dict], role: str = "evaluation") -> list[dict]:
    """Per scene, n and iterations: ``sparse`` - each other recipe, paired by seed."""
    by = defaultdict(dict)
    for r in rows:
        if r["role"] == role:
            by[(r["scene"], r["n"], r["iterations"])][(r["recipe"], r["seed"])] = r
    out = []
    for (scene, n, its), runs in by.items():
        recipes = sorted({k[0] for k in runs} - {OURS})
        for other in recipes:
            seeds = sorted(s for (rc, s) in runs if rc == OURS and (other, s) in runs)
            if not seeds:
                continue
            d = {"scene": scene, "n": n, "iterations": its, "against": other, "seeds": seeds}
            for m in ("psnr", "ssim", "lpips_alex", "lpips_vgg"):
                d[m] = _interval([runs[(OURS, s)][m] - runs[(other, s)][m] for s in seeds
                                  if runs[(OURS, s)][m] is not None and runs[(other, s)][m] is not None])
            if other == BASE:  # sparse's final against paper's best along its run, per seed
                d["final_minus_paper_best"] = _interval([runs[(OURS, s)]["psnr"] - runs[(BASE, s)]["best_psnr"]
                                                         for s in seeds if runs[(BASE, s)].get("best_psnr")])
            out.append(d)
    return out


def _mean_psnr(per: dict[str, dict[str, dict]], scenes: list[str]) -> dict[str, float]:
    """Each recipe's mean over ``scenes`` of its per-scene mean final PSNR (``per``: recipe ->
    scene -> aggregate row)."""
    return {rc: sum(v[s]["psnr"]["mean"] for s in scenes) / len(scenes) for rc, v in per.items()}


def _lead(mean_psnr: dict[str, float]) -> float | None:
    """``sparse``'s mean PSNR minus the best other recipe's (None without both)."""
    others = [m for rc, m in mean_psnr.items() if rc != OURS]
    return mean_psnr[OURS] - max(others) if OURS in mean_psnr and others else None


def spread(per: dict[str, dict[str, dict]], scenes: list[str], kinds: dict[str, str]) -> dict:
    """How the lead over the best other recipe is spread over the scenes. ``per``: recipe ->
    scene -> aggregate row (every recipe on every one of ``scenes``); ``kinds``: scene -> kind.

    Returns ``by_kind`` (per kind: its scenes, each recipe's mean final PSNR over them, the lead
    there), ``sparse_best_scenes`` (where ``sparse``'s mean is the highest of the recipes) and,
    from two scenes on, ``lead_leave_one_out`` (the lead over the other scenes with each one left
    out: its lowest and highest, and which scene was out)."""
    out: dict = {"by_kind": {}, "sparse_best_scenes": []}
    for kind in sorted({kinds.get(s) or "unknown" for s in scenes}):
        sc = [s for s in scenes if (kinds.get(s) or "unknown") == kind]
        m = _mean_psnr(per, sc)
        out["by_kind"][kind] = {"scenes": sc, "mean_final_psnr": m, "psnr_lead_over_best_other": _lead(m)}
    if OURS in per:
        out["sparse_best_scenes"] = [s for s in scenes if all(per[OURS][s]["psnr"]["mean"] >= v[s]["psnr"]["mean"]
                                                               for v in per.values())]
    if OURS in per and len(per) > 1 and len(scenes) > 1:
        loo = sorted((_lead(_mean_psnr(per, [x for x in scenes if x != s])), s) for s in scenes)
        out["lead_leave_one_out"] = {"min": loo[0][0], "min_without": loo[0][1],
                                     "max": loo[-1][0], "max_without": loo[-1][1]}
    return out


def verdicts(rows: list[dict], agg: list[dict], pairs: list[dict], n: int = TARGET_N,
             iterations: int | None = None, kinds: dict[str, str] | None = None,
             floors: dict[str, dict[int, float]] | None = None) -> dict:
    """The targets, computed on the evaluation scenes at ``n`` views and ``iterations`` (None:
    the most iterations any evaluation run has at ``n``); the targets are stated at
    :data:`TARGET_N`, other view counts get the same measures. None where data is missing.
    ``kinds`` (scene -> kind, from the protocol) groups :func:`spread`'s means; ``floors``
    ({scene: {n: PSNR}}, :mod:`experiments.sparse_views.floor`) gives the floor row. The
    scene-level readings (floor, equal backgrounds, intervals, covered pixels) are
    :mod:`experiments.sparse_views.scene_level`'s."""
    if iterations is None:
        iterations = max((r["iterations"] for r in rows if r["role"] == "evaluation" and r["n"] == n), default=0)
    # the named recipes only: a variant kept beside them (an earlier version, `mcmc-r13`) is
    # in the table, never in the targets
    ev = [a for a in agg if a["role"] == "evaluation" and a["n"] == n and a["iterations"] == iterations
          and a["recipe"] in RECIPE_NAMES]
    recipes = {a["recipe"] for a in ev}
    # a scene counts once every recipe has run on it (a grid still running leaves some out)
    have = defaultdict(set)
    for a in ev:
        have[a["scene"]].add(a["recipe"])
    scenes = sorted(sc for sc, rs in have.items() if rs == recipes)
    out = {"n": n, "iterations": iterations, "evaluation_scenes": scenes,
           "incomplete_scenes": sorted(set(have) - set(scenes)),
           # the recipes with no run here at their current values (a changed recipe's earlier
           # runs are kept under a variant's name, splat_train.recipes.VARIANTS)
           "recipes_without_runs": [rc for rc in RECIPE_NAMES if rc not in recipes]}
    ev = [a for a in ev if a["scene"] in scenes]
    rows = [r for r in rows if r["role"] == "evaluation" and r["n"] == n and r["iterations"] == iterations
            and r["scene"] in scenes]
    if not ev:
        return out
    out["floor"] = scene_level.floor_block(rows, scenes, floors or {}, n, OURS)
    out["equal_background"] = scene_level.equal_background(rows, scenes)
    out["scene_level"] = scene_level.scene_level_intervals(rows, scenes, OURS)
    out["coverage"] = scene_level.coverage(rows, scenes)
    # mean over scenes of each recipe's mean final PSNR (recipes present on every scene)
    per = defaultdict(dict)
    for a in ev:
        per[a["recipe"]][a["scene"]] = a
    full = {rc: v for rc, v in per.items() if set(v) == set(scenes)}
    mean_psnr = _mean_psnr(full, scenes)
    out["mean_final_psnr"] = mean_psnr
    out["spread"] = spread(full, scenes, kinds or {})
    if OURS in mean_psnr:
        out["psnr_lead_over_best_other"] = _lead(mean_psnr)
        out["psnr_lead_ok"] = (out["psnr_lead_over_best_other"] or 0) >= 0.5
    if OURS in mean_psnr and BASE in mean_psnr:  # against paper as it trains now
        vp = [p for p in pairs if p["n"] == n and p["iterations"] == iterations and p["against"] == BASE
              and p["scene"] in scenes]
        for net in ("lpips_alex", "lpips_vgg"):
            # paired over every (scene, seed) of the evaluation scenes
            diffs = [r_o[net] - r_b[net] for r_o, r_b in _pairs(rows, BASE, n) if r_o[net] is not None and r_b[net] is not None]
            iv = _interval(diffs)
            out[f"{net}_minus_paper"] = iv
            # no worse: the interval of (sparse - paper) does not lie wholly above zero
            out[f"{net}_no_worse"] = None if iv["k"] < 2 else iv["mean"] - iv["hw95"] <= 0
        out["final_ge_paper_best_scenes"] = sum(1 for p in vp if p.get("final_minus_paper_best", {}).get("mean") is not None
                                                and p["final_minus_paper_best"]["mean"] >= 0)
    if OURS in mean_psnr:
        out["max_gaussians_ours"] = max((r["gaussians"] for r in rows if r["recipe"] == OURS), default=None)
        out["gaussians_ok"] = out["max_gaussians_ours"] is not None and out["max_gaussians_ours"] <= MAX_GAUSSIANS
    return out


def _pairs(rows, other, want_n):
    idx = {(r["scene"], r["n"], r["iterations"], r["recipe"], r["seed"]): r for r in rows if r["role"] == "evaluation"}
    for (scene, n, its, rc, seed), r in idx.items():
        if rc == OURS and n == want_n and (scene, n, its, other, seed) in idx:
            yield r, idx[(scene, n, its, other, seed)]


def _fmt(iv: dict, m: str) -> str:
    if iv["mean"] is None:
        return "n/a"
    d = 0 if m in ("gaussians", "train_s") else (3 if m in ("ssim", "lpips_alex", "lpips_vgg") else 2)
    s = f"{iv['mean']:,.{d}f}"
    return s if iv["hw95"] is None else f"{s} ± {iv['hw95']:,.{d}f}"


GENERATED = "Generated by `python -m experiments.sparse_views summary`"
"""The line that marks a table this command wrote: ``summary --doc FILE`` replaces only a file
that holds it (or writes a new one)."""


def check_doc(doc: Path, generated: str = GENERATED) -> None:
    """Refuse a ``--doc`` a command may not write: a link, a folder, or a file it did not
    generate (one without its ``generated`` line in the first 4 KiB: :data:`GENERATED` for
    ``summary``; every command that writes a generated page passes its own). Nothing is written.

    Also refused: a ``doc`` whose nearest existing folder is a file or cannot be written
    (its missing folders are made when the page is written).

    Raises:
        ValueError: one line naming the file and what to do.
    """
    import os

    above = next((a for a in Path(os.path.abspath(doc)).parents if a.exists()), None)
    if above is not None and not above.is_dir():
        raise ValueError(f"--doc {doc}: {above} is a file, not a folder: name a file in a folder (nothing was changed)")
    if above is not None and not os.access(above, os.W_OK | os.X_OK):
        raise ValueError(f"--doc {doc}: the folder {above} cannot be written here: name a file in a writable folder "
                         "(nothing was changed)")
    if doc.is_symlink():
        raise ValueError(f"--doc {doc} is a symbolic link: name the file itself (nothing was changed)")
    if doc.exists() and not doc.is_file():
        raise ValueError(f"--doc {doc} is not a file: name a new file or a table this command wrote")
    if doc.is_file():
        with open(doc, "rb") as f:
            head = f.read(4096).decode("utf-8", errors="replace")
        if generated not in head:
            raise ValueError(f"--doc {doc} exists and was not written by this command (no line "
                             f"'{generated}'): move it away or name a new file (nothing was changed)")


def registration_sentence(block: dict) -> str:
    """The grid's registration block (:func:`experiments.sparse_views.provenance.check_scenes`) as one
    sentence of a page."""
    from experiments.sparse_views.provenance import sentence

    return sentence(block, f"commits that gave each evaluation scene its `role: evaluation` in `{block['file']}`")


def markdown(agg: list[dict], pairs: list[dict], verdict: dict, scenes, by_n: dict | None, runs_dir: str,
             registration: dict | None = None) -> str:
    info = {s.name: s for s in scenes}
    lines = ["# Sparse-view results: tuning and evaluation scenes apart", "",
             f"{GENERATED} from the run records in",
             f"`{runs_dir}`; do not edit by hand. Every cell: `posed` initialiser",
             "(reference cameras, points triangulated from the n training views, however few; random points,",
             "3DGS's random initialisation, only where they triangulate none: experiments/sparse_views/cells.py),",
             "every 8th image held out, final-iteration scores of the held-out views (mean ± 95 % t half-width",
             "over seeds). Recipe values were chosen on the tuning scenes only (docs/lessons.md says which",
             "runs chose each); a `sparse-*` row of the tuning scenes is a variant of `sparse` tried there",
             "(`sparse-r2`: `sparse` before the opacity regulariser; `sparse-r3`: before growth stopped at half",
             "the run; `sparse-r10`: before binocular consistency; `sparse-r11`: before the opacity decay and",
             "growth to the end of the run; `sparse-r12`: binocular consistency from 2/3 of the run, not from",
             "the densification start; `sparse-r13`: against black, before the training images' mean colour",
             "behind the model). `mcmc-r13` is `mcmc-keep` (below) before its growth rule (5 % per refine",
             "step alone, which leaves a seed of a few triangulated points far below its cap; kept beside the",
             "rerun, outside the targets). Each record's config is what a run of its values is asked now",
             "(`sparse-r13`: `sparse` with a black background; `mcmc-r13`: `mcmc-keep` with the growth rule",
             "`gsplat`). `paper-seedcode`, `dropgaussian-wsprune` and `mcmc-keep` are `paper`,",
             "`dropgaussian` and `mcmc` before they took their releases' values (the seed code's schedule; 3DGS's",
             "world-size prune, which DropGaussian's release never runs; a seed that fills the cap kept at its",
             "size): kept beside the recipes, outside the targets, until the recipes are run again.",
             "`paper-bgmean` is `paper-seedcode` against the training images' mean colour",
             "instead of black (`sparse`'s colour), so that the lead is also read at",
             "equal background; outside the targets. On a scene with a `background` in scenes.yaml (NeRF's",
             "synthetic scenes: white) every recipe trains and renders against it; on the others `sparse`",
             "trains against the mean colour and the field's recipes against black.", ""]
    if registration:
        lines += [registration_sentence(registration), ""]
    for role in ("evaluation", "tuning"):
        rs = [a for a in agg if a["role"] == role]
        if not rs:
            continue
        lines += [f"## {role.capitalize()} scenes", "",
                  "| scene | kind | n | iterations | recipe | seeds | " + " | ".join(HEAD[m] for m in MEASURES) + " |",
                  "|---|---|---|---|---|---|" + "---|" * len(MEASURES)]
        for a in rs:
            kind = info[a["scene"]].kind if a["scene"] in info else ""
            lines.append(f"| {a['scene']} | {kind} | {a['n']} | {a['iterations']} | {a['recipe']} | {len(a['seeds'])} | "
                         + " | ".join(_fmt(a[m], m) for m in MEASURES) + " |")
        lines.append("")
    if pairs:
        lines += ["## `sparse` against each recipe, paired by seed (evaluation scenes)", "",
                  "| scene | n | against | Δ PSNR | Δ SSIM | Δ LPIPS-Alex | Δ LPIPS-VGG | final − paper's best PSNR |",
                  "|---|---|---|---|---|---|---|---|"]
        for p in pairs:
            best = _fmt(p["final_minus_paper_best"], "psnr") if "final_minus_paper_best" in p else ""
            lines.append(f"| {p['scene']} | {p['n']} | {p['against']} | " + " | ".join(
                _fmt(p[m], m) for m in ("psnr", "ssim", "lpips_alex", "lpips_vgg")) + f" | {best} |")
        lines.append("")
    for (n, its), v in (by_n or {(verdict.get("n", TARGET_N), verdict.get("iterations")): verdict}).items():
        if not v.get("mean_final_psnr"):
            continue
        lines += [f"## Targets (evaluation scenes, n = {n}, {its} iterations)" if n == TARGET_N else
                  f"## The same measures at n = {n}, {its} iterations (the targets are stated at n = {TARGET_N})",
                  ""]
        if v.get("incomplete_scenes"):
            lines.append("- not counted until every recipe has run there: " + ", ".join(v["incomplete_scenes"]))
        if v.get("recipes_without_runs"):
            lines.append("- no figure below is of " + ", ".join(f"`{rc}`" for rc in v["recipes_without_runs"])
                         + " with the values they now train with, and no target against them is read (the "
                         "variant rows above hold their runs with their earlier values)")
        lines += _scene_level_lines(v)
        lines.append("- mean final PSNR over the scenes, each recipe at its own background: "
                     + ", ".join(f"{k} {x:.2f}" for k, x in v["mean_final_psnr"].items()))
        if "psnr_lead_over_best_other" in v and v["psnr_lead_over_best_other"] is not None:
            lines.append(f"- `sparse` − best other recipe, each at its own background (not a like-for-like "
                         f"comparison; the equal-background lines above are): {v['psnr_lead_over_best_other']:+.2f} dB "
                         f"(target ≥ +0.5: {'met' if v['psnr_lead_ok'] else 'not met'})")
        sp = v.get("spread", {})
        if len(sp.get("by_kind", {})) > 1:
            lines.append("- by kind of scene: " + "; ".join(
                f"{kind} ({len(k['scenes'])}): " + ", ".join(f"{rc} {x:.2f}" for rc, x in k["mean_final_psnr"].items())
                + ("" if k["psnr_lead_over_best_other"] is None else f", `sparse` − best other {k['psnr_lead_over_best_other']:+.2f} dB")
                for kind, k in sp["by_kind"].items()))
        if OURS in v["mean_final_psnr"] and len(v["mean_final_psnr"]) > 1:
            rest = [s for s in v["evaluation_scenes"] if s not in sp.get("sparse_best_scenes", [])]
            lines.append(f"- scenes where `sparse` has the highest mean PSNR of the recipes: "
                         f"{len(sp.get('sparse_best_scenes', []))} of {len(v['evaluation_scenes'])}"
                         + (f" (not on {', '.join(rest)})" if rest else ""))
        if sp.get("lead_leave_one_out"):
            lo = sp["lead_leave_one_out"]
            lines.append(f"- the lead with one scene left out: {lo['min']:+.2f} dB (without {lo['min_without']}) "
                         f"to {lo['max']:+.2f} dB (without {lo['max_without']})")
        for net in ("lpips_alex", "lpips_vgg"):
            if f"{net}_minus_paper" in v:
                lines.append(f"- {HEAD[net]} `sparse` − `paper`, paired over scenes and seeds: "
                             f"{_fmt(v[net + '_minus_paper'], net)} (no worse: "
                             f"{ {True: 'met', False: 'not met', None: 'n/a'}[v[net + '_no_worse']] })")
        if "final_ge_paper_best_scenes" in v:
            lines.append(f"- scenes where `sparse`'s final PSNR ≥ `paper`'s best along its run: "
                         f"{v['final_ge_paper_best_scenes']} of {len(v['evaluation_scenes'])}")
        if v.get("max_gaussians_ours") is not None:
            lines.append(f"- largest `sparse` model: {v['max_gaussians_ours']:,} Gaussians (target ≤ {MAX_GAUSSIANS:,}: "
                         f"{'met' if v['gaussians_ok'] else 'not met'})")
        lines.append("")
    return "\n".join(lines)


def _iv(iv: dict, m: str = "psnr", sign: bool = True) -> str:
    """A scene-level interval as ``+0.47 [−0.95, +1.90] (k = 5)``."""
    if iv.get("mean") is None:
        return "n/a"
    d = 2 if m == "psnr" else 3
    f = (lambda x: f"{x:+.{d}f}") if sign else (lambda x: f"{x:.{d}f}")
    body = f(iv["mean"]) if iv.get("lo") is None else f"{f(iv['mean'])} [{f(iv['lo'])}, {f(iv['hi'])}]"
    return f"{body} (k = {iv['k']})"


def _scene_level_lines(v: dict) -> list[str]:
    """The scene-level readings of one view count (:mod:`experiments.sparse_views.scene_level`)."""
    out = []
    fl = v.get("floor")
    if fl:
        out.append(f"- floor, a flat image of the training views' mean colour: {fl['psnr']:.2f} dB; `{fl['recipe']}` − floor "
                   f"{_iv(fl['lead'])}, {fl['lead']['scenes_ahead']} of {len(fl['psnr_per_scene'])} scenes above it "
                   f"(target ≥ +{fl['target']:.1f}: {'met' if fl['met'] else 'not met'})")
    else:
        out.append("- floor: not measured for every scene (`python -m experiments.sparse_views floor`)")
    for eb in v.get("equal_background", []):
        d = eb["diff"]
        out.append(f"- at equal background ({eb['background']}): `{eb['ours']}` {eb['mean_psnr'][eb['ours']]:.2f} against "
                   f"`{eb['base']}` {eb['mean_psnr'][eb['base']]:.2f}; PSNR {_iv(d['psnr'])}, "
                   f"{d['psnr']['scenes_ahead']} of {len(d['psnr']['per_scene'])} scenes ahead; "
                   f"LPIPS-Alex {_iv(d['lpips_alex'], 'lpips_alex')}, LPIPS-VGG {_iv(d['lpips_vgg'], 'lpips_vgg')} "
                   f"(target ≥ +{eb['target']:.1f} dB with the interval above 0 and LPIPS no worse: "
                   f"{'met' if eb['met'] else 'not met'})")
    if v.get("scene_level"):
        out.append("- `sparse` − each other recipe, PSNR with the scene as the unit: " + "; ".join(
            f"{k} {_iv(iv)}" for k, iv in v["scene_level"].items()))
    if v.get("coverage"):
        out.append("- covered pixels (accumulated alpha ≥ 0.5; share covered, PSNR over them, full-image PSNR; "
                   "SSIM and LPIPS-Alex over them where every run scored them): " + "; ".join(
            f"{k} {c['coverage']:.2f}, {c['psnr_covered']:.2f}, {c['psnr']:.2f}"
            + (f", SSIM {c['ssim_covered']:.3f}" if "ssim_covered" in c else "")
            + (f", LPIPS-Alex {c['lpips_covered']:.3f}" if "lpips_covered" in c else "")
            for k, c in v["coverage"].items()))
    return out


def write_summary(records: Path, doc: Path, scenes, protocol: Path | None = None) -> dict:
    """Write ``records/summary.json`` and the page ``doc``; with the scenes file ``protocol``,
    also the ``registration`` block: per evaluation scene with runs here, the commit that gave it
    its role against the times of its runs (:mod:`experiments.sparse_views.provenance`)."""
    check_doc(doc)
    files = record_files(records)
    rows = [r for _, r in files]
    agg, pairs = aggregate(rows), paired(rows)
    # the targets at n = TARGET_N and the most iterations run there; every (n, iterations) measured
    kinds = {s.name: s.kind for s in scenes}
    floors = load_floors(records)
    verdict = verdicts(rows, agg, pairs, kinds=kinds, floors=floors)
    by_n = {(n, its): verdicts(rows, agg, pairs, n, its, kinds=kinds, floors=floors)
            for n, its in sorted({(r["n"], r["iterations"]) for r in rows if r["role"] == "evaluation"})}
    summary = {"rows": [{k: r[k] for k in RECORD_KEYS} | {"best_psnr": r.get("best_psnr")} for r in rows],
               "aggregate": agg, "paired": pairs, "targets": verdict,
               "measures_by_n": {f"n{n}_i{its}": v for (n, its), v in by_n.items()}}
    if protocol is not None:
        from experiments.sparse_views.provenance import check_scenes

        evaluation = {s.name for s in scenes if s.role == "evaluation"}
        runs_of: dict[str, list[Path]] = defaultdict(list)
        for p, r in files:
            if r["scene"] in evaluation:
                runs_of[r["scene"]].append(p)
        shown = protocol.resolve().relative_to(REPO) if protocol.resolve().is_relative_to(REPO) else protocol
        summary["registration"] = check_scenes(protocol, dict(runs_of), str(shown))
    with atomic_path(records / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1) + "\n")
    doc.parent.mkdir(parents=True, exist_ok=True)
    runs_dir = (records / "runs").resolve()
    shown = runs_dir.relative_to(REPO) if runs_dir.is_relative_to(REPO) else runs_dir
    with atomic_path(doc) as tmp:  # a link put there meanwhile is replaced, never followed
        tmp.write_text(markdown(agg, pairs, verdict, scenes, by_n, f"{shown}/", summary.get("registration")))
    print(doc.read_text())
    return summary
