"""Figures that a backdrop cannot fake, with the scene as the unit.

Three readings of the evaluation scenes beside the summary's means, each computed from the
same records:

- **the floor**: a flat image of the training views' mean colour scored like a model
  (:mod:`experiments.sparse_views.floor`), and ``sparse`` − floor per scene;
- **equal backgrounds**: ``sparse`` against ``paper`` with both trained and rendered against
  the same colour, once on black (the field's background for real captures: ``sparse``'s
  records under :data:`EQUAL_BACKGROUND`'s black name) and once on the training views' mean
  colour (``paper``'s records under its mean-colour name);
- **covered pixels**: per recipe, the share of held-out pixels the model covers (accumulated
  alpha >= 0.5, splat_train/training/heldout.py) and the PSNR over them, from the runs that recorded it.

Every difference is first averaged over the seeds of a scene, then summarised over the scenes
(95 % t interval, :func:`evaluation.study.stats.t_interval`, k = the number of scenes), so one
scene's many seeds cannot narrow the interval.
"""

from __future__ import annotations

from collections import defaultdict

#: (background, ``sparse``'s records there, ``paper``'s records there): each pair trained and
#: rendered against one colour. ``sparse-r13`` is ``sparse`` with every value as now but the
#: background (black; its records' config ``{"recipe": "sparse", "background": [0, 0, 0]}``);
#: ``paper-seedcode`` is ``paper`` with the seed code's schedule (its runs before ``paper`` took
#: the 3DGS release's), and ``paper-bgmean`` is ``paper-seedcode`` against the training views'
#: mean colour, so both pairs hold the same ``paper``.
EQUAL_BACKGROUND = (("black", "sparse-r13", "paper-seedcode"), ("mean colour", "sparse", "paper-bgmean"))
#: the lead over the floor the default recipe must reach at the target view count (dB)
FLOOR_LEAD_TARGET = 3.0
#: the lead over ``paper`` at equal background the default recipe must reach (dB), with the
#: scene-level interval above zero
EQUAL_BACKGROUND_TARGET = 0.5
COMPARED = ("psnr", "ssim", "lpips_alex", "lpips_vgg")

__all__ = ["EQUAL_BACKGROUND", "interval", "scene_means", "scene_interval", "floor_block", "equal_background",
           "scene_level_intervals", "coverage"]


def interval(values: list[float]) -> dict:
    """Mean, 95 % t half-width, its ends and k of ``values`` (None where k is too small for one)."""
    from evaluation.study.stats import t_interval

    mean, hw, k = t_interval(values)
    ok = k > 0
    return {"mean": mean if ok else None, "hw95": hw if k > 1 else None,
            "lo": mean - hw if k > 1 else None, "hi": mean + hw if k > 1 else None, "k": k}


def scene_means(rows: list[dict], recipe: str, scenes: list[str], measure: str) -> dict[str, float]:
    """{scene: mean over its seeds of ``measure``} for ``recipe``'s runs (``rows``: the records of
    one n and budget); scenes without a run, or with a missing value, are left out."""
    vals = defaultdict(list)
    for r in rows:
        if r["recipe"] == recipe and r["scene"] in scenes and r.get(measure) is not None:
            vals[r["scene"]].append(float(r[measure]))
    return {s: sum(v) / len(v) for s, v in vals.items()}


def scene_interval(rows: list[dict], ours: str, other: str, scenes: list[str], measure: str = "psnr") -> dict:
    """``ours`` − ``other`` in ``measure``, per scene over the seeds both ran, then over the
    scenes where both ran: the interval (:func:`interval`), the per-scene differences and how
    many scenes are ahead (a higher PSNR/SSIM, a lower LPIPS)."""
    a, b = defaultdict(dict), defaultdict(dict)
    for r in rows:
        if r["scene"] in scenes and r.get(measure) is not None:
            if r["recipe"] == ours:
                a[r["scene"]][r["seed"]] = float(r[measure])
            elif r["recipe"] == other:
                b[r["scene"]][r["seed"]] = float(r[measure])
    per = {}
    for s in scenes:
        seeds = sorted(set(a[s]) & set(b[s]))
        if seeds:
            per[s] = sum(a[s][k] - b[s][k] for k in seeds) / len(seeds)
    sign = -1.0 if measure.startswith("lpips") else 1.0
    return {**interval(list(per.values())), "per_scene": per,
            "scenes_ahead": sum(sign * d > 0 for d in per.values())}


def floor_block(rows: list[dict], scenes: list[str], floors: dict[str, dict[int, float]], n: int,
                ours: str = "sparse") -> dict | None:
    """The floor at ``n`` views over ``scenes`` and ``ours`` − floor per scene (None unless
    every scene has a floor)."""
    per = {s: floors.get(s, {}).get(n) for s in scenes}
    if not scenes or any(v is None for v in per.values()):
        return None
    mine = scene_means(rows, ours, scenes, "psnr")
    diffs = {s: mine[s] - per[s] for s in scenes if s in mine}
    lead = interval(list(diffs.values()))
    return {"psnr_per_scene": per, "psnr": sum(per.values()) / len(per), "recipe": ours,
            "lead": {**lead, "per_scene": diffs, "scenes_ahead": sum(d > 0 for d in diffs.values())},
            "target": FLOOR_LEAD_TARGET,
            "met": lead["mean"] is not None and len(diffs) == len(scenes) and lead["mean"] >= FLOOR_LEAD_TARGET}


def equal_background(rows: list[dict], scenes: list[str]) -> list[dict]:
    """Per pair of :data:`EQUAL_BACKGROUND` whose records cover every scene: each side's mean
    PSNR, and ours − paper per measure with the scene as the unit; ``met``: the PSNR lead is
    at least :data:`EQUAL_BACKGROUND_TARGET` with its interval above zero and LPIPS (both
    networks) no worse (the interval of ours − paper not wholly above zero)."""
    out = []
    for background, ours, base in EQUAL_BACKGROUND:
        have = {r["scene"] for r in rows if r["recipe"] == ours} & {r["scene"] for r in rows if r["recipe"] == base}
        if not scenes or not set(scenes) <= have:
            continue
        d = {m: scene_interval(rows, ours, base, scenes, m) for m in COMPARED}
        p = d["psnr"]
        lpips_ok = all(d[m]["lo"] is None or d[m]["lo"] <= 0 for m in ("lpips_alex", "lpips_vgg"))
        out.append({"background": background, "ours": ours, "base": base,
                    "mean_psnr": {k: sum(v.values()) / len(v) for k, v in
                                  ((ours, scene_means(rows, ours, scenes, "psnr")),
                                   (base, scene_means(rows, base, scenes, "psnr")))},
                    "diff": d, "target": EQUAL_BACKGROUND_TARGET,
                    "met": (p["k"] > 1 and p["mean"] >= EQUAL_BACKGROUND_TARGET and p["lo"] > 0 and lpips_ok)})
    return out


def scene_level_intervals(rows: list[dict], scenes: list[str], ours: str = "sparse") -> dict[str, dict]:
    """``ours`` − every other recipe or variant that ran on all ``scenes``, in PSNR, with the
    scene as the unit (:func:`scene_interval`)."""
    names = sorted({r["recipe"] for r in rows} - {ours})
    return {other: scene_interval(rows, ours, other, scenes)
            for other in names
            if set(scenes) <= {r["scene"] for r in rows if r["recipe"] == other}}


def coverage(rows: list[dict], scenes: list[str]) -> dict[str, dict]:
    """Per recipe or variant, over ``scenes`` (per-scene means over seeds, then their mean):
    the share of held-out pixels covered at the end of the run, the PSNR over them, and the
    full-image PSNR of the same runs; only recipes whose every run on those scenes recorded
    coverage (the held-out curve's last ``coverage`` and ``psnr_covered``). The SSIM and LPIPS
    over the covered pixels (``ssim_covered``, ``lpips_covered``) are added where every one of
    those runs recorded them (runs before the trainer scored them did not)."""
    by = defaultdict(list)
    for r in rows:
        if r["scene"] in scenes:
            by[r["recipe"]].append(r)
    out = {}
    for recipe, rs in sorted(by.items()):
        curves = [r.get("curve") or {} for r in rs]
        if any(not c.get("coverage") or not c.get("psnr_covered") for c in curves):
            continue
        if {r["scene"] for r in rs} != set(scenes):
            continue
        measures = ["coverage", "psnr_covered"] + [m for m in ("ssim_covered", "lpips_covered")
                                                   if all(c.get(m) and c[m][-1] is not None for c in curves)]
        flat = [{"scene": r["scene"], "recipe": recipe, "seed": r["seed"], "psnr": r["psnr"],
                 **{m: c[m][-1] for m in measures}} for r, c in zip(rs, curves)]
        out[recipe] = {m: sum(v.values()) / len(v) for m in (*measures, "psnr")
                       for v in [scene_means(flat, recipe, scenes, m)]}
    return out
