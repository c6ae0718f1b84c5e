"""One renderer per section of docs/results.md, each reading its records.

Every renderer takes its records folder (``experiments/records``, for the GPU sections
``benchmarks/records``, or a copy) and returns the
section's body lines, or ``None`` when its record is not there (:mod:`experiments.results_doc.page`).
Figures come from the records only; the fixed text says what the figures are not.
"""

from __future__ import annotations

import json
import re
from collections import defaultdict
from pathlib import Path

from experiments.results_doc.page import REPO, RECORDS, iv, latest, load, table, verdict
from experiments.sparse_views.seeds import REGISTERED, REMEASURED, target_text

SUMMARY = "sparse_views/summary.json"
LLFF_RUNS = "llff_protocol/runs"
MVS_TUNING_RUNS = "mvs_tuning/runs"
GPU = "gpu-*.json"
PROTOCOLS = "protocols-*.json"
SEMANTICS = "backend_semantics-*.json"


def _seeds(seeds) -> str:
    seeds = sorted(seeds)
    return f"seed {seeds[0]}" if len(seeds) == 1 else "seeds " + ", ".join(map(str, seeds))


def _device(name: str) -> str:
    return {"cpu": "CPU", "cuda": "GPU"}.get(name, name)


def _mean(xs) -> float:
    xs = list(xs)
    return sum(xs) / len(xs)


# --- training recipes on the evaluation scenes -----------------------------------------------------

def sparse_views(records: Path) -> list[str] | None:
    """The targets at equal background with the floor, the scene-level intervals and the covered
    pixels (summary.json's ``measures_by_n``, :mod:`experiments.sparse_views.scene_level`)."""
    p = records / SUMMARY
    if not p.is_file():
        return None
    s = load(p)
    by_n = sorted(s["measures_by_n"].values(), key=lambda v: (v["n"], v["iterations"]))
    by_n = [v for v in by_n if v.get("mean_final_psnr")]
    if not by_n:
        return None
    agg = [a for a in s["aggregate"] if a["role"] == "evaluation"]

    def seeds(v):
        return max(len(a["seeds"]) for a in agg if a["n"] == v["n"] and a["iterations"] == v["iterations"])

    head = ["reading", *(f"n = {v['n']}, {v['iterations']:,} it, {seeds(v)} seeds" for v in by_n)]
    rows: dict[str, list[str]] = defaultdict(lambda: [""] * len(by_n))
    for i, v in enumerate(by_n):
        k = len(v["evaluation_scenes"])
        fl = v.get("floor")
        if fl:
            rows["floor: a flat image of the training views' mean colour, dB"][i] = f"{fl['psnr']:.2f}"
            rows[f"`{fl['recipe']}` − floor (target ≥ +{fl['target']:.1f})"][i] = (
                f"{iv(fl['lead'])}, above on {fl['lead']['scenes_ahead']} of {k}: {verdict(fl['met'])}")
        for eb in v.get("equal_background", []):
            o, b, d = eb["ours"], eb["base"], eb["diff"]
            rows[f"equal background, {eb['background']}: `{o}` − `{b}` (target ≥ +{eb['target']:.1f}, "
                 "interval above 0)"][i] = (
                f"{eb['mean_psnr'][o]:.2f} − {eb['mean_psnr'][b]:.2f}: {iv(d['psnr'])}, ahead on "
                f"{d['psnr']['scenes_ahead']} of {k}: {verdict(eb['met'])}")
            rows[f"equal background, {eb['background']}: LPIPS-Alex / VGG, `{o}` − `{b}`"][i] = (
                f"{iv(d['lpips_alex'], 3)} / {iv(d['lpips_vgg'], 3)}")
        for r in ("sparse", "paper", "paper-seedcode"):
            c = v.get("coverage", {}).get(r)
            if c:
                rows[f"`{r}`: held-out pixels covered (alpha ≥ 0.5), PSNR over them"][i] = (
                    f"{c['coverage']:.2f}, {c['psnr_covered']:.2f}")
        if v.get("psnr_lead_over_best_other") is not None:
            rows["`sparse` − best of the field's recipes, each at its own background (target ≥ +0.5)"][i] = (
                f"{v['psnr_lead_over_best_other']:+.2f}: {verdict(v['psnr_lead_ok'])}")
        if v.get("max_gaussians_ours") is not None:
            rows["largest `sparse` model, Gaussians (target ≤ 60,000)"][i] = (
                f"{v['max_gaussians_ours']:,}: {verdict(v['gaussians_ok'])}")
    out = table(head, [[k, *c] for k, c in rows.items()])

    # each recipe's mean over the scenes, and sparse minus it with the scene as the unit
    recipes = ["sparse"] + sorted({a["recipe"] for a in agg} - {"sparse"})
    head2 = ["recipe"]
    for v in by_n:
        head2 += [f"n = {v['n']}: PSNR", "LPIPS-Alex", "Gaussians", "`sparse` − it"]
    rows2 = []
    for rc in recipes:
        row, seen = [f"`{rc}`"], False
        for v in by_n:
            sc = v["evaluation_scenes"]
            mine = {a["scene"]: a for a in agg if a["recipe"] == rc and a["n"] == v["n"]
                    and a["iterations"] == v["iterations"] and a["scene"] in sc}
            if set(mine) != set(sc):
                row += ["", "", "", ""]
                continue
            seen = True
            row += [f"{_mean(mine[x]['psnr']['mean'] for x in sc):.2f}",
                    f"{_mean(mine[x]['lpips_alex']['mean'] for x in sc):.3f}",
                    f"{_mean(mine[x]['gaussians']['mean'] for x in sc) / 1000:.1f}k",
                    "" if rc == "sparse" else iv(v.get("scene_level", {}).get(rc))]
        if seen:
            rows2.append(row)
    from experiments.sparse_views.summary import TARGET_N, registration_sentence
    from splat_train.recipes import VARIANTS

    missing = sorted({rc for v in by_n for rc in v.get("recipes_without_runs", [])})
    kept = [name for name in VARIANTS if any(a["recipe"] == name for a in agg)]
    gap = [] if not missing else [
        "No figure above is of " + ", ".join(f"`{rc}`" for rc in missing) + " with the values they now train "
        "with (docs/reference.md section 7), and no target is read against them"
        + ("" if not kept else "; " + ", ".join(f"`{x}`" for x in kept) + " are their runs before their values "
           "changed") + ".", ""]
    return out + ["", *table(head2, rows2), "", *gap,
                  "Evaluation scenes, on which no recipe value was chosen (`experiments/sparse_views/scenes.yaml`):",
                  ", ".join(f"`{x}`" for x in by_n[0]["evaluation_scenes"]) + ". `posed` seed, every 8th image "
                  "held out, on a CPU.",
                  "Means over the scenes of each scene's mean over seeds; intervals are 95 % t intervals with the",
                  f"scene as the unit. The targets are stated at n = {TARGET_N}; other view counts get the same "
                  "measures.",
                  "`sparse` trains against the training views' mean colour and the field's recipes against black,",
                  "so the like-for-like rows are those at equal background (`sparse-r13`: `sparse` on black;",
                  "`paper-bgmean`: `paper-seedcode` on the mean colour). Per scene, and every tuning run:",
                  "`docs/results-sparse-views.md`.",
                  *([registration_sentence(s["registration"])] if s.get("registration") else [])]


# --- the dense mvs seed ----------------------------------------------------------------------------

def _registration(name: str, records: Path = RECORDS):
    """The record of a pre-registered seed comparison, with its run and report commands (the run
    command as its records under ``records`` hold the registration: :func:`seeds.as_recorded`)."""
    from experiments.sparse_views import seeds

    path = REGISTERED / f"{name}.yaml"
    if not path.is_file():
        path = REMEASURED / f"{name}.yaml"
    reg = seeds.load_registration(path)
    rel = seeds.records_dir(reg).relative_to(RECORDS)
    report = (f"`{seeds.run_command(seeds.as_recorded(reg, records / rel))}`, then `python -m experiments.sparse_views.seeds report "
              f"--registration {path.relative_to(REPO)} --work WORK`")
    return rel / f"{reg['name']}.json", report


def _seed_tables(rep: dict) -> list[str]:
    sc = rep["complete_scenes"]
    rows = []
    for v in rep["variants"]:
        per = [rep["per_scene"][v][s] for s in sc]
        if not per:
            continue
        m = {k: _mean(r[k] for r in per) for k in per[0]}
        rows.append([f"`{v}`", f"{m['psnr']:.2f}", f"{m['lpips_alex']:.3f} / {m['lpips_vgg']:.3f}",
                     f"{m['coverage']:.2f}", f"{m['seed_gaussians'] / 1000:.1f}k / {m['gaussians'] / 1000:.1f}k"])
    floors = [rep["floor_psnr"][s] for s in sc if rep["floor_psnr"].get(s) is not None]
    if floors:
        rows.append(["floor (flat mean colour)", f"{_mean(floors):.2f}", "", "", ""])
    out = table(["variant", "PSNR", "LPIPS-Alex / VGG", "held-out pixels covered", "seed / final Gaussians"], rows)
    comp = []
    for c in rep["comparisons"]:
        target = target_text(c, "≥")
        met = verdict(c["met"]) if c["kind"] == "target" else ""
        if c["kind"] == "target" and len(sc) < len(rep["scenes"]):
            met = "incomplete"
        lp = c.get("lpips_alex_diff")
        comp.append([f"`{c['better']}` − `{c['than']}`", iv(c["psnr_diff"]),
                     f"{c['scenes_ahead']} of {c['scenes']}", "" if lp is None else f"{lp['mean']:+.3f}", target, met])
    return out + ["", *table(["PSNR difference", "mean [95 % interval], scene as unit", "scenes ahead",
                              "LPIPS-Alex difference", "target", "verdict"], comp)]


def _seed_section(name: str, text: list[str]):
    def render(records: Path) -> list[str] | None:
        rel, _ = _registration(name)
        if not (records / rel).is_file():
            return None
        rep = load(records / rel)
        from experiments.sparse_views.seeds import kept_sentence

        from experiments.sparse_views.seeds import backgrounds

        recipes = ", ".join(f"`{r}`" for r in dict.fromkeys(v["recipe"] for v in rep["variants"].values()))
        bg = backgrounds(rep["variants"])
        head = (f"{rep['runs']} of {rep['runs_expected']} runs: {len(rep['scenes'])} scenes, n = {rep['n']}, "
                f"{_seeds(rep['seeds'])}, {rep['iterations']:,} iterations, {recipes} "
                + ("on black." if bg.endswith("(black)") else f"({bg})."))
        if rep.get("kept"):
            head += " " + kept_sentence(rep["kept"])
        if rep.get("scenes_measured_before"):
            from experiments.sparse_views.seeds import measured_sentence

            head += " " + measured_sentence(rep["scenes_measured_before"], len(rep["scenes"]))
        if rep.get("registration"):  # whether its commit came before every run, as the report found it
            from experiments.sparse_views.provenance import sentence

            head += " " + sentence(rep["registration"], f"commit that added `{rep['registration']['file']}`")
        return [*_seed_tables(rep), "", head, *text]
    return render


baselines_released = _seed_section("baselines_released", [
    "The default recipe against 3DGS as its authors release it (`paper`, docs/reference.md section 7), its",
    "values fixed in a commit before these runs, on captures that only `paper-seedcode` runs had measured:",
    "at the field's equal background (black, `sparse-black`), and as a user gets it (`sparse`, on the",
    "training views' mean colour) against the floor. Per scene: `docs/results-baselines-released.md`."])

released_dropgaussian_mcmc = _seed_section("released_dropgaussian_mcmc", [
    "The default recipe on black against DropGaussian and 3DGS-MCMC as their authors release them, on the",
    "same captures, its values fixed before these runs; `sparse-black` was run again into these records and",
    "repeated its runs above to the bit. Per scene: `docs/results-released-dropgaussian-mcmc.md`."])

mvs_fill_seed = _seed_section("mvs_fill_seed", [
    "`paper-seedcode` from four seeds on captures no run had measured before the registration was committed:",
    "triangulated points (`paper-seedcode`: `posed`), 3DGS's random points, and `mvs` with every unexplained",
    "ray filled, its opacity from Eq. 2 (`gated`) or uniform. Per scene: `docs/results-mvs-fill-seed.md`."])

mvs_seed = _seed_section("mvs_seed", [
    "The same comparison on the sparse-view evaluation scenes, with `mvs` writing only the pixels it",
    "kept (no fill). Where three views triangulate no point, `posed` falls back to the random points,",
    "so `paper-seedcode` and `paper-random` coincide there. Per scene: `docs/results-mvs-seed.md`."])

MVS_TUNING_TEXT = [
    "`paper-seedcode` (`paper` before it took its release's values) from each seed on two tuning scenes. Record names: `-s20` reads every 20th pixel (the",
    "Bridge's stride; otherwise every pixel), `-nofill` keeps only the pixels stereo explains, `-fill1`",
    "fills every unexplained ray (the default now); `paper-mvs` filled every 4th pixel",
    "(`experiments/records/mvs_tuning/README.md`)."]


def mvs_tuning(records: Path) -> list[str] | None:
    runs = [load(p) for p in latest(records, f"{MVS_TUNING_RUNS}/*.json")]
    if not runs:
        return None
    scenes = sorted({r["scene"] for r in runs})
    psnr = {(r["recipe"], r["scene"]): r["psnr"] for r in runs}
    rows = [[f"`{rc}`", *(f"{psnr[(rc, s)]:.2f}" if (rc, s) in psnr else "" for s in scenes)]
            for rc in sorted({r["recipe"] for r in runs})]
    its = sorted({r["iterations"] for r in runs})
    return [*table(["seed (record name)", *(f"{s} PSNR" for s in scenes)], rows), "",
            f"n = {runs[0]['n']}, {_seeds({r['seed'] for r in runs})}, {', '.join(f'{i:,}' for i in its)} iterations, black.",
            *MVS_TUNING_TEXT]


# --- the field's LLFF protocol ---------------------------------------------------------------------

#: the field's 8-scene means (docs/field.md has the sources)
PUBLISHED_LLFF = (("3DGS, random points", 15.52, 0.408, "DNGaussian paper"),
                  ("3DGS, MVS points", 19.22, 0.649, "CoR-GS paper, Table 1"),
                  ("FSGS", 20.43, 0.682, "FSGS paper"),
                  ("CoR-GS", 20.45, 0.712, "CoR-GS paper"),
                  ("DropGaussian", 20.76, 0.713, "DropGaussian paper, Table 1"))


def _llff_runs(records: Path) -> list[dict]:
    return [load(p) for p in latest(records, f"{LLFF_RUNS}/*.json")]


def llff_protocol(records: Path) -> list[str] | None:
    runs = _llff_runs(records)
    if not runs:
        return None
    rows = []
    for r in sorted(runs, key=lambda r: r["scene"]):
        c = r.get("curve") or {}
        cov = (f"{c['psnr_covered'][-1]:.2f} ({c['coverage'][-1]:.2f})"
               if c.get("coverage") and c.get("psnr_covered") else "")
        rows.append([r["scene"], f"{r['psnr']:.2f}", f"{r['ssim']:.3f}", f"{r['lpips_alex']:.3f}",
                     f"{r['lpips_vgg']:.3f}", cov, f"{r['gaussians']:,}", f"{r['train_s']:.0f}"])
    k = len(runs)
    m = {x: _mean(r[x] for r in runs) for x in ("psnr", "ssim", "lpips_alex", "lpips_vgg", "gaussians", "train_s")}
    rows.append([f"mean of {k}", f"{m['psnr']:.2f}", f"{m['ssim']:.3f}", f"{m['lpips_alex']:.3f}",
                 f"{m['lpips_vgg']:.3f}", "", f"{m['gaussians']:,.0f}", f"{m['train_s']:.0f}"])
    its = ", ".join(f"{i:,}" for i in sorted({r["iterations"] for r in runs}))
    seeds = _seeds({r["seed"] for r in runs})
    device = ", ".join(sorted({_device(str(r.get("device") or r.get("backend"))) for r in runs}))
    pub = [[name, f"{p:.2f}", f"{s:.3f}", "8", src] for name, p, s, src in PUBLISHED_LLFF]
    pub.append([f"this project, `{runs[0]['recipe']}`", f"{m['psnr']:.2f}", f"{m['ssim']:.3f}", str(k),
                f"the table above ({its} iterations, {seeds}, {device})"])
    return [*table(["scene", "PSNR", "SSIM", "LPIPS-Alex", "LPIPS-VGG", "PSNR covered (share)", "Gaussians",
                     "train s"], rows), "",
            *table(["method", "PSNR", "SSIM", "scenes", "source"], pub), "",
            "LLFF at 1/8 resolution, every 8th image held out, 3 training views spread over the rest with the",
            "dataset's poses; `sparse` on black seeded by `mvs` (Bridge `gated`). The published figures are",
            "8-scene means at 10,000 iterations on GPUs (`docs/field.md`). Not comparable with them: `leaves`",
            "is in no public repository with its photos; every scene here is a tuning scene of this project",
            f"(its values were chosen on some of them); {seeds} and {its} iterations on a {device}, where",
            "the papers train 10,000 (DropGaussian reports the best of five runs); the 3 views are the rounded",
            "`linspace` over the training pool and fern is undistorted, where the papers take their own",
            "split's views and the raw images. \"covered\": held-out pixels with accumulated alpha ≥ 0.5."]


def llff_command(records: Path) -> str:
    """The run line for the LLFF protocol, its variant and budget taken from the records."""
    runs = _llff_runs(records)
    if not runs:
        return ("`python -m experiments.sparse_views --protocol experiments/llff_protocol/scenes.yaml --records "
                "experiments/records/llff_protocol run --role tuning --n 3 --seeds 0 --work WORK --recipes VARIANT`")
    r = runs[0]
    spec = f"{r['recipe']}={json.dumps(r['config'], separators=(',', ':'))}"
    return ("`python -m experiments.sparse_views --protocol experiments/llff_protocol/scenes.yaml --records "
            f"experiments/records/llff_protocol run --role {r['role']} --n {r['n']} --seeds {r['seed']} "
            f"--iterations {r['iterations']} --work WORK --recipes '{spec}'`")


# --- both evaluation protocols ---------------------------------------------------------------------

def protocols(records: Path) -> list[str] | None:
    found = latest(records, PROTOCOLS)
    if not found:
        return None
    rec = load(found[-1])
    rows = []
    for init, c in rec["cells"].items():
        t, pose = c["train"], c.get("testpose_record") or {}
        rows.append([f"`{init}`", f"{c['strict']['psnr']:.2f} / {c['strict']['ssim']:.3f}",
                     f"{c['test-pose']['psnr']:.2f} / {c['test-pose']['ssim']:.3f}",
                     f"{pose.get('mean_rotation_deg', float('nan')):.2f}°",
                     f"`{t['recipe']}`, {t['iterations']:,} it, {t['rasterizer']}, {t['num_gaussians']:,} Gaussians"])
    p = rec["prepared"]
    return [*table(["seed", "[strict] PSNR / SSIM", "[test-pose] PSNR / SSIM",
                    "held-out camera moved by test-pose, mean", "training"], rows), "",
            f"{p['scene']}, n = {p['n']}, on {rec.get('gpu') or rec.get('device')}. `[strict]` renders each",
            "held-out view at the reference camera mapped by the Sim(3) fitted on the training cameras;",
            "`[test-pose]` first refines that camera against its photo with the model frozen",
            f"({rec['testpose_steps']} steps; `docs/protocols.md`). Fern is a tuning scene."]


# --- the GPU records -------------------------------------------------------------------------------

def gpu_parts(records: Path) -> dict:
    """Every part of the GPU records, each from the latest record that holds it."""
    merged: dict = {}
    for p in latest(records, GPU):
        merged.update(load(p))
    return merged


GPU_TABLE_PARTS = ("device", "torch", "cuda", "gsplat", "gsplat_build", "cell", "native", "cell_sparse",
                   "rasterizer_timing", "workflow_cell", "vggt_fixtures", "vggt_chunked", "vggt_cli")


def gpu(records: Path) -> list[str] | None:
    from experiments.results_doc.gpu_table import format_gpu_table

    r = gpu_parts(records)
    if "cell" not in r:
        return None
    return [*format_gpu_table({k: r[k] for k in GPU_TABLE_PARTS if k in r}).splitlines(), "",
            "Each part from the latest `benchmarks/records/gpu-*.json` that holds it (each record's `runs`",
            "say which call made which part); a recipe changed since its part ran is not rerun. \"cell\":",
            "fern at 1/8, n = 3, COLMAP seed, 10,000 iterations; fern is a tuning scene, so its held-out",
            "figures here are not evidence of quality. Same-row figures come from one call: compare",
            "only within a row. The step profiles (`profile`, `profile_late`, `step_ab`) are in the records."]


# --- do the backends agree -------------------------------------------------------------------------

SEMANTICS_TEXT = {"cpu": "none (the CPU kernel)",
                  "visibility": "a Gaussian below opacity 1/255 not counted as seen by the densification",
                  "clamp999": "alpha clamped at 0.999 instead of 3DGS's 0.99",
                  "clamp999+op": "alpha at 0.999, opacities clamped at 0.99 before the render (the gsplat adapter)"}


def backends(records: Path) -> list[str] | None:
    found = latest(records, SEMANTICS)
    if not found:
        return None
    rec = load(found[-1])
    rows = []
    for recipe, block in ((rec["recipe"], rec), *((b["recipe"], b) for b in [rec.get("paper")] if b)):
        for variant, s in block["summary"].items():
            d = s.get("minus_cpu")
            rows.append([f"`{recipe}`", SEMANTICS_TEXT.get(variant, variant), str(s["seeds"]),
                         f"{s['mean']:.2f} (sd {s['sd']:.2f})", "" if not d else f"{d['mean']:+.2f} ± {d['hw95']:.2f}"])
    agree = gpu_parts(records).get("backend_agree", {})
    for recipe, b in agree.get("by_recipe", {}).items():
        a = b.get("all_records") or {}
        rows.append([f"`{recipe}`", f"{agree.get('rasterizer')} on the GPU (latest `backend_agree`)", str(len(b["seeds"])),
                     f"{b['this_psnr']:.2f} (sd {b['this_seed_sd']:.2f})",
                     f"{b['psnr_diff']:+.2f} ± {b['psnr_diff_hw95']:.2f} paired by seed"
                     + (f"; {a['psnr_diff']:+.2f} ± {a['psnr_diff_hw95']:.2f} against all {a['seeds']} CPU seeds"
                        if a else "")])
    return [*table(["recipe", "gsplat's semantics emulated on the CPU kernel", "seeds", "final held-out PSNR",
                    "minus the CPU kernel (95 %)"], rows), "",
            f"The sparse-view grid's cell `{rec['cell']}`, {rec['iterations']:,} iterations, each semantics in the C++",
            "kernel's training one at a time, paired by seed. The gsplat row sets gsplat's runs beside the grid's",
            "CPU records of the same cell: `GSPLAT_BUILD_BG=1 AGREE_SEEDS=3-6 AGREE_RECIPES=sparse bash",
            "scripts/gpu_run.sh OUT backend_agree`."]


# --- VGGT at many frames ---------------------------------------------------------------------------

def vggt(records: Path) -> list[str] | None:
    r = gpu_parts(records)
    parts = [r[k] for k in ("vggt_frames", "vggt_many", "vggt_search") if isinstance(r.get(k), dict)]
    real, probe = {}, {}
    for part in parts:
        real.update({x["frames"]: x for x in part.get("real", []) if x.get("peak_mb") is not None})
        probe.update({x["frames"]: x for x in part.get("probe", []) if x.get("peak_mb") is not None})
    if not real:
        return None
    rows = [[f"{f:,}", f"{x['wall_s']:.3g}", f"{x['s_per_frame']:.3f}",
             f"{probe[f]['peak_mb']:,.0f}" if f in probe else "", f"{x['peak_mb']:,.0f}"]
            for f, x in sorted(real.items())]
    search = next((p["search"] for p in reversed(parts) if p.get("search", {}).get("largest_fit_frames")), None)
    out = table(["frames", "forward s", "s per frame", "peak GPU MiB, probe", "peak GPU MiB, real"], rows)
    p0 = parts[0]
    if search:
        pred = (r.get("derived") or {}).get("vggt_time_at_largest_fit") or {}
        up = p0.get("upstream", {})
        out += ["", *table(["largest count that fits (memory probe)", "its peak MiB", "first count out of memory",
                            "predicted forward s there", "upstream VGGT"],
                           [[f"{search['largest_fit_frames']:,}", f"{search['largest_fit_peak_mb']:,.0f}",
                             f"{search.get('first_oom_frames', ''):,}",
                             f"{pred['predicted_s']:,.0f}" if pred.get("predicted_s") else "",
                             f"about {up.get('frames', '?'):,} frames on {up.get('memory_gb', '?')} GB"]])]
    return out + ["", f"VGGT-1B at {p0['size']}, trunk in bf16, camera + point heads, random weights (speed and",
                  f"memory only), on {p0.get('device_name', 'a GPU')}. The probe (`fastpath.memory_probe()`) allocates",
                  "attention's output without computing it, so its peak is the real forward's and its time is not.",
                  "How the forward keeps memory per frame low: `benchmarks/vggt_frames.py`'s docstring."]


# --- the robustness catalogue ----------------------------------------------------------------------

def robustness(records: Path) -> list[str] | None:
    doc = REPO / "docs" / "robustness.md"
    section, n = None, 0
    for line in doc.read_text().splitlines():
        if line.startswith("## "):
            section = line[3:].strip()
        elif section == "Catalogue" and re.match(r"^\|\s*\d+\s*\|", line):
            n += 1
    return [f"{n} stiff, extreme and bad-input cases in the catalogue's table, each with the test that holds",
            "it; the input cases also run through each stage's command line."]
