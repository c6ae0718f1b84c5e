"""Read a results tree into one record per run (tolerant of missing pieces).

Layout (workflow/rules/common.smk): a run is ``{results}/{dataset}/{scene}/n{n}/{init}/``
(``init`` = vggt, colmap, oracle, ...), optionally split into bridge-mode sub-folders
``{init}/{mode}/`` (gated, uniform, filtered; any sub-folder holding ``bridge/``, ``train/`` or
``metrics.json``), each one record. Every file below is looked up by name at any depth,
shallowest first: in the mode folder, then in the run folder outside every mode folder
(initialiser outputs such as status.json and pose.json are shared by the modes), ignoring
``repeats/`` (COLMAP repeat runs) and ``ckpt/``:

=================  ==========================================================================
file               what is read
=================  ==========================================================================
``status.json``    initialiser status (COLMAP baseline): ``success``, ``aligned_ok``,
                   ``registered``, ``n_images``, ``points``, ``reason``, ``wall_time_s``,
                   ``peak_rss_mb``, ``fy_over_fx``, ``repeats`` (spread over seeds), ``fallback``
                   (column ``seed_fallback``: its ``reason`` when ``applied``)
``pose.json``      :mod:`evaluation.metrics.pose`: ATE, RPE, relative rotation error, fy/fx, success
``metrics.json``   ``python -m evaluation images``: means ``psnr``, ``ssim``, ``lpips_alex``,
                   ``lpips_vgg`` (top level, or under ``mean``), ``wall_time_s``; ``coverage``
                   (the share of held-out pixels the model covers), ``covered`` (the four
                   measures over those pixels alone: columns ``covered_psnr``, ...) and
                   ``covered_alpha`` (the threshold on accumulated alpha); null or absent: NaN
``timing.json``    vggt_init / oracle: ``total_s`` (or ``wall_time_s``), peak memory keys
``bridge.json``    bridge: ``mode``, ``wall_time_s``
``train.json``     splat_train summary: ``wall_time_s`` (or ``train_s``), ``num_gaussians``
``log.parquet``    training log: iteration, wall_time_s, loss, test_psnr, num_gaussians
                   (held-out PSNR at the final and at the best evaluated iteration)
``*.tsv``          Snakemake benchmark files (columns ``s``, ``max_rss`` in MB); also looked
                   for under ``{results}/benchmarks/{dataset}/{scene}/n{n}/{init}/``; a file's
                   stage is guessed from its name (init/vggt/colmap/oracle, bridge, train,
                   eval/metrics/pose/render)
``align.json``     ``train_cameras`` (column ``heldout_cameras``): which training cameras the
                   held-out Sim(3) used; ``align_refined/align.json`` (pose refinement on) wins
``renders/``       rendered test views (report only)
``testpose/``      the test-pose protocol (docs/protocols.md), read only from the mode (or run)
                   folder's ``testpose/``, never by the name look-up above:
                   ``testpose/metrics.json`` (columns ``testpose_psnr``, ``testpose_ssim``,
                   ``testpose_lpips_alex``, ``testpose_lpips_vgg``, ``testpose_coverage``,
                   ``testpose_covered_psnr``, ...) and
                   ``testpose/refine/testpose.json`` (``testpose_rot_deg_mean``,
                   ``testpose_steps``, ``testpose_patience``)
``floor.json``     ``python -m evaluation floor``, one per (dataset, scene, n) at
                   ``{results}/{dataset}/{scene}/n{n}/floor.json`` (beside the initialiser
                   folders): the flat image of the training views' mean colour, scored like a
                   render (columns ``floor_psnr``, ``floor_ssim``, ``floor_lpips_alex``,
                   ``floor_lpips_vgg``; the same for every run of that scene and n)
=================  ==========================================================================

A scene without reference cameras has no ``pose.json``; a failed COLMAP run has only
``status.json``. Missing numbers are NaN / None, never zero.

Success (docs/contracts.md, one definition): ``success_paper`` = status.json's (>= 1 registered
image and >= 1 point) when a status exists, else pose.json's, else "the run produced a trained
model or metrics". ``success_gated`` = paper success, >= 3 registered training views and the
accuracy gate on pose.json (:func:`evaluation.metrics.pose.accuracy_gate`); None for scenes without reference cameras (no run of the scene has a pose.json);
False for a run of a scene with reference cameras that has no pose.json itself.
"""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path

import pandas as pd

from evaluation.initialisers import registry
from evaluation.metrics.pose import GateConfig, accuracy_gate, status_success
from evaluation.reports.markup import counted
from runtime.checks import check_folder

__all__ = ["RUN_COLUMNS", "IMAGE_MEASURES", "COVERAGE_COLUMNS", "FLOOR_COLUMNS", "FLOOR_FILE", "run_label", "mode_dirs", "find_runs", "find_file", "read_log", "best_along", "read_run",
           "collect_runs", "STAGES"]

log = logging.getLogger(__name__)

_N_DIR = re.compile(r"^n(\d+)$")
_SKIP = {"repeats", "ckpt", "testpose"}  # testpose/: the second protocol's files, read by name
TESTPOSE_DIR = "testpose"
"""A mode's folder of the test-pose protocol (``testpose/metrics.json``, ``testpose/refine/``)."""
#: The held-out evaluation protocols (docs/protocols.md) -> the prefix of their metric columns;
#: the strict one (the paper's) first, the default of every table.
PROTOCOLS = {"strict": "", "test-pose": "testpose_"}
#: The held-out metrics of each protocol: the strict column name -> the test-pose column name.
#: The image measures of a metrics.json (and of a floor.json).
IMAGE_MEASURES = ("psnr", "ssim", "lpips_alex", "lpips_vgg")
TESTPOSE_COLUMNS = {k: PROTOCOLS["test-pose"] + k for k in IMAGE_MEASURES}
#: The coverage columns of each protocol (strict column name -> the protocol's): the share of
#: held-out pixels covered, and each image measure over the covered pixels alone.
COVERAGE_COLUMNS = ("coverage", *(f"covered_{k}" for k in IMAGE_MEASURES))
#: The floor's columns (floor.json's measure -> column); the floor is the same under both protocols.
FLOOR_COLUMNS = {k: f"floor_{k}" for k in IMAGE_MEASURES}
FLOOR_FILE = "floor.json"
"""The floor of a (dataset, scene, n): ``{results}/{dataset}/{scene}/n{n}/floor.json``."""
STAGES = ("init", "bridge", "train", "eval")
_STAGE_WORDS = {"init": ("init", *registry.NAMES), "bridge": ("bridge",),
                "train": ("train", "splat"), "eval": ("eval", "metric", "pose", "render", "align")}

RUN_COLUMNS = [
    "dataset", "scene", "n", "init", "bridge_mode", "success_paper", "success_gated", "has_reference",
    "registered", "n_train", "points", "reason", *IMAGE_MEASURES, "n_test",
    *(prefix + c for prefix in PROTOCOLS.values() for c in COVERAGE_COLUMNS), "covered_alpha",
    *FLOOR_COLUMNS.values(), "ate_rmse", "ate_rel_radius", "ate_pct_radius", "rpe_rot_deg", "rpe_trans_dir_deg",
    *TESTPOSE_COLUMNS.values(), "testpose_rot_deg_mean", "testpose_steps", "testpose_patience",
    "rel_rot_err_mean_deg", "rel_rot_err_max_deg", "fy_fx_max_dev", "final_test_psnr", "best_test_psnr", "best_test_iter", "num_gaussians",
    "iterations", "recipe", "init_s", "bridge_s", "train_s", "eval_s", "total_s", "peak_mem_mb", "peak_gpu_mb",
    "repeats", "repeats_success_rate", "repeats_registered_min", "repeats_registered_max", "heldout_cameras",
    "seed_fallback", "run_dir",
]


_RESERVED = {"sparse", "repeats", "benchmarks", "logs", "ckpt", "init", "eval", "train", "bridge",
             "renders", "align", "align_refined", "cameras_refined"}


def mode_dirs(run_dir: Path) -> list[Path]:
    """Bridge-mode sub-folders of a run (``{init}/{mode}/`` holding bridge/, train/ or
    metrics.json), sorted; empty for a flat run or an initialiser-only (failed) run."""
    return sorted(p for p in run_dir.iterdir() if p.is_dir() and p.name not in _RESERVED
                  and ((p / "bridge").is_dir() or (p / "train").is_dir() or (p / "metrics.json").is_file()))


def run_label(init: str, mode) -> str:
    """Display name of an (initialiser, bridge mode) pair: the initialiser's label (the
    registry's), alone or with the mode, "label (mode)"."""
    name = registry.label(init)
    return name if mode is None or (isinstance(mode, float) and math.isnan(mode)) else f"{name} ({mode})"


_RUN_FILES = ("status.json", "timing.json", "pose.json", "metrics.json", "bridge.json", "train.json",
              "log.parquet")


def find_runs(results: str | Path, warn: bool = True) -> list[tuple[Path, str | None]]:
    """(run folder ``{results}/{dataset}/{scene}/n{n}/{init}``, bridge mode or None), sorted.

    A run folder with mode sub-folders gives one entry per mode; otherwise one entry with None.
    A run folder without any result file (only logs: the job never wrote its outputs) is left
    out, with a warning unless ``warn`` is False.
    """
    results = Path(results)
    check_folder(results, "results folder")
    out = []
    for p in sorted(results.glob("*/*/n*/*")):
        if not (p.is_dir() and _N_DIR.match(p.parent.name)) or p.parts[-4] == "benchmarks":
            continue
        if not any(find_file(p, name) for name in _RUN_FILES):
            # only logs: the job never produced a result (e.g. VGGT without its checkpoint);
            # that is a run that did not happen, not a failure of the method
            if warn:
                log.warning("%s holds no result files (see its logs/): left out of the tables", p)
            continue
        modes = mode_dirs(p)
        out += [(p, m.name) for m in modes] if modes else [(p, None)]
    return out


def find_file(run_dir: Path, name: str, skip: set[str] = frozenset(), mode: str | None = None) -> Path | None:
    """The shallowest file (or folder) called ``name`` for a run: first under
    ``run_dir/mode`` (when a mode is given), then under ``run_dir`` outside its mode
    sub-folders; repeats/ and ckpt/ are skipped, and top-level folders named in ``skip``.
    None when absent."""
    run_dir = Path(run_dir)
    if mode is not None:
        hit = find_file(run_dir / mode, name)
        if hit is not None:
            return hit
        skip = set(skip) | {m.name for m in mode_dirs(run_dir)}
    best = None
    for p in run_dir.rglob(name):
        rel = p.relative_to(run_dir).parts
        if _SKIP & set(rel[:-1]) or (len(rel) > 1 and rel[0] in skip):
            continue
        if best is None or (len(rel), str(p)) < (len(best.relative_to(run_dir).parts), str(best)):
            best = p
    return best


def read_log(path: Path | None) -> pd.DataFrame | None:
    """The training log ``log.parquet`` at ``path``; None where there is none or it cannot be
    read (logged)."""
    if path is None or not Path(path).is_file():
        return None
    try:
        return pd.read_parquet(path)
    except (OSError, ValueError) as exc:
        log.warning("results: cannot read %s (%s)", path, exc)
        return None


def best_along(lg: pd.DataFrame | None, col: str, higher: bool = True) -> tuple[float, float]:
    """The best value of the log's column ``col`` along the run (the highest, or the lowest with
    ``higher=False``) and its iteration; NaN where the log lacks the column or every value is null."""
    v = lg[col].dropna() if lg is not None and col in lg else pd.Series(dtype=float)
    if v.empty:
        return math.nan, math.nan
    i = v.idxmax() if higher else v.idxmin()
    return float(v[i]), float(lg.loc[i, "iteration"]) if "iteration" in lg else math.nan


def _json(path: Path | None) -> dict:
    if path is None:
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        log.warning("results: cannot read %s (%s); treated as missing", path, exc)
        return {}
    return data if isinstance(data, dict) else {}


def _num(value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return math.nan
    return v


def _first(d: dict, *keys) -> float:
    for k in keys:
        if k in d and d[k] is not None:
            return _num(d[k])
    return math.nan


def _metric(m: dict, key: str) -> float:
    v = m.get(key)
    if isinstance(v, dict):
        v = v.get("mean")
    if v is None:
        for nest in ("mean", "means"):
            if isinstance(m.get(nest), dict):
                v = m[nest].get(key)
    return _num(v)


def _coverage(m: dict, prefix: str) -> dict[str, float]:
    """A metrics.json's coverage and its measures over the covered pixels (keys
    :data:`COVERAGE_COLUMNS` after the protocol's ``prefix``); NaN where null or absent (a
    metrics.json scored without alpha)."""
    covered = m.get("covered") if isinstance(m.get("covered"), dict) else {}
    values = {"coverage": _num(m.get("coverage")), **{f"covered_{k}": _num(covered.get(k)) for k in IMAGE_MEASURES}}
    return {prefix + k: values[k] for k in COVERAGE_COLUMNS}


def _peaks(d: dict) -> tuple[float, float]:
    """(peak host MB, peak GPU MB) from any keys naming a peak in MB/GB."""
    host, gpu = math.nan, math.nan
    for k, v in d.items():
        kl = k.lower()
        if "peak" not in kl or isinstance(v, (dict, list)):
            continue
        val = _num(v) * (1024.0 if kl.endswith("gb") else 1.0)
        if math.isnan(val):
            continue
        if "gpu" in kl or "cuda" in kl or "vram" in kl:
            gpu = val if math.isnan(gpu) else max(gpu, val)
        else:
            host = val if math.isnan(host) else max(host, val)
    return host, gpu


def _benchmarks(run_dir: Path, bench_dir: Path | None, mode: str | None = None) -> dict[str, dict]:
    """stage -> {"s": seconds (summed), "max_rss": MB (max)} from Snakemake benchmark TSVs
    (the run's own and its mode's; other modes' are skipped)."""
    others = {m.name for m in mode_dirs(run_dir)} - {mode}
    files = [p for p in run_dir.rglob("*.tsv")
             if not (_SKIP & set(p.relative_to(run_dir).parts)) and p.relative_to(run_dir).parts[0] not in others]
    if bench_dir is not None and bench_dir.is_dir():
        files += sorted(bench_dir.glob("*.tsv"))
    out: dict[str, dict] = {}
    for f in files:
        try:
            df = pd.read_csv(f, sep="\t")
        except (OSError, ValueError, pd.errors.ParserError) as exc:
            log.warning("results: cannot read benchmark %s (%s)", f, exc)
            continue
        if "s" not in df.columns or df.empty:
            continue
        stem = f.stem.lower()
        stage = next((s for s in STAGES if any(w in stem for w in _STAGE_WORDS[s])), None)
        if stage is None:
            continue
        rec = out.setdefault(stage, {"s": 0.0, "max_rss": math.nan})
        rec["s"] += float(pd.to_numeric(df["s"], errors="coerce").mean())
        if "max_rss" in df.columns:
            rss = float(pd.to_numeric(df["max_rss"], errors="coerce").max())
            rec["max_rss"] = rss if math.isnan(rec["max_rss"]) else max(rec["max_rss"], rss)
    return out


def read_run(run_dir: str | Path, gate: GateConfig = GateConfig(), results_root: Path | None = None,
             mode: str | None = None) -> dict:
    """One run's record (keys :data:`RUN_COLUMNS`); see the module docstring.

    Args:
        run_dir: ``{results}/{dataset}/{scene}/n{n}/{init}``.
        mode: the bridge-mode sub-folder to read (None: a flat run).
    """
    run_dir = Path(run_dir)
    init, n_dir, scene, dataset = run_dir.name, run_dir.parent.name, run_dir.parent.parent.name, \
        run_dir.parent.parent.parent.name
    n = int(_N_DIR.match(n_dir).group(1))
    find = lambda name: find_file(run_dir, name, mode=mode)  # noqa: E731
    status = _json(find("status.json"))
    pose = _json(find("pose.json"))
    metrics = _json(find("metrics.json"))
    tp_dir = (run_dir / mode if mode else run_dir) / TESTPOSE_DIR
    tp_metrics = _json(tp_dir / "metrics.json" if (tp_dir / "metrics.json").is_file() else None)
    floor_path = run_dir.parent / FLOOR_FILE
    floor = _json(floor_path if floor_path.is_file() else None)
    tp_record = _json(tp_dir / "refine" / "testpose.json" if (tp_dir / "refine" / "testpose.json").is_file() else None)
    timing = _json(find("timing.json"))
    bridge = _json(find("bridge.json"))
    train = _json(find("train.json"))
    log_path = find("log.parquet")
    bench_dir = results_root / "benchmarks" / dataset / scene / n_dir / init if results_root else None
    bench = _benchmarks(run_dir, bench_dir, mode)

    if status:
        success = status_success(status)
    elif pose:
        success = bool(pose.get("success_paper", False))
    else:
        success = bool(metrics or train or log_path)
    has_ref = bool(pose) and pose.get("has_reference", True)
    gated = accuracy_gate({**pose, "success_paper": success, "has_reference": has_ref}, gate)
    registered = status.get("registered", pose.get("registered", n if success and not status else None))

    rec = {
        "dataset": dataset, "scene": scene, "n": n, "init": init,
        "bridge_mode": bridge.get("mode", mode), "success_paper": success, "success_gated": gated,
        "has_reference": has_ref, "registered": _num(registered), "n_train": n,
        "points": _first(status, "points") if status else _first(pose, "n_points"),
        "reason": status.get("reason"),
        # the random-point fallback's reason when the run trained from it (evaluation/initialisers/random_init.py)
        "seed_fallback": (status.get("fallback") or {}).get("reason")
        if (status.get("fallback") or {}).get("applied") else None,
        **{k: _metric(metrics, k) for k in ("psnr", "ssim", "lpips_alex", "lpips_vgg")},
        "n_test": _first(metrics, "n_images"),
        **{tp: _metric(tp_metrics, k) for k, tp in TESTPOSE_COLUMNS.items()},
        **_coverage(metrics, PROTOCOLS["strict"]), **_coverage(tp_metrics, PROTOCOLS["test-pose"]),
        "covered_alpha": _first(metrics, "covered_alpha") if metrics.get("covered_alpha") is not None
        else _first(tp_metrics, "covered_alpha"),
        **{col: _num(floor.get(k)) for k, col in FLOOR_COLUMNS.items()},
        "testpose_rot_deg_mean": _first(tp_record, "mean_rotation_deg"),
        "testpose_steps": _first(tp_record, "steps"),
        "testpose_patience": _first(tp_record, "patience"),
        **{k: _first(pose, k) for k in ("ate_rmse", "ate_rel_radius", "ate_pct_radius", "rpe_rot_deg",
                                         "rpe_trans_dir_deg", "rel_rot_err_mean_deg", "rel_rot_err_max_deg",
                                         "fy_fx_max_dev")},
        "final_test_psnr": math.nan, "best_test_psnr": math.nan, "best_test_iter": math.nan,
        "num_gaussians": _first(train, "num_gaussians", "final_num_gaussians"),
        "iterations": _first(train, "iterations", "iteration"),
        # the training recipe (splat_train/recipes.py); a train.json from before recipes: paper
        "recipe": (train.get("recipe") or "paper") if train else None,
        "run_dir": str(run_dir / mode if mode else run_dir),
    }
    if math.isnan(rec["fy_fx_max_dev"]) and status.get("fy_over_fx") is not None:
        rec["fy_fx_max_dev"] = abs(_num(status["fy_over_fx"]) - 1.0)
    lg = read_log(log_path)
    log_time = math.nan
    if lg is not None:
        if "test_psnr" in lg and lg["test_psnr"].notna().any():
            rec["final_test_psnr"] = float(lg["test_psnr"].dropna().iloc[-1])
        rec["best_test_psnr"], rec["best_test_iter"] = best_along(lg, "test_psnr")
        if math.isnan(rec["num_gaussians"]) and "num_gaussians" in lg and len(lg):
            rec["num_gaussians"] = float(lg["num_gaussians"].iloc[-1])
        if math.isnan(rec["iterations"]) and "iteration" in lg and len(lg):
            rec["iterations"] = float(lg["iteration"].max())
        if "wall_time_s" in lg and len(lg):
            log_time = float(lg["wall_time_s"].max())

    json_times = {
        "init": _first(timing, "total_s", "wall_time_s", "total") if timing else _first(status, "wall_time_s"),
        "bridge": _first(bridge, "wall_time_s", "total_s"),
        "train": _first(train, "wall_time_s", "train_s", "total_s", "time_s"),
        "eval": (_first(metrics, "wall_time_s") if metrics else math.nan),
    }
    if math.isnan(json_times["train"]):
        json_times["train"] = log_time
    if pose and not math.isnan(_first(pose, "wall_time_s")):
        json_times["eval"] = (0.0 if math.isnan(json_times["eval"]) else json_times["eval"]) + _num(pose["wall_time_s"])
    for stage in STAGES:
        v = json_times[stage]
        if math.isnan(v) and stage in bench:
            v = bench[stage]["s"]
        rec[f"{stage}_s"] = v
    parts = [rec[f"{s}_s"] for s in STAGES if not math.isnan(rec[f"{s}_s"])]
    rec["total_s"] = sum(parts) if parts else math.nan
    host, gpu = math.nan, math.nan
    for d in (timing, status, train, bridge):
        h, g = _peaks(d)
        host = h if math.isnan(host) else (host if math.isnan(h) else max(host, h))
        gpu = g if math.isnan(gpu) else (gpu if math.isnan(g) else max(gpu, g))
    for b in bench.values():
        if not math.isnan(b["max_rss"]):
            host = b["max_rss"] if math.isnan(host) else max(host, b["max_rss"])
    rec["peak_mem_mb"], rec["peak_gpu_mb"] = host, gpu

    refined = (run_dir / mode if mode else run_dir) / "align_refined" / "align.json"
    align = _json(refined if refined.is_file() else find("align.json"))
    rec["heldout_cameras"] = align.get("train_cameras", "initialiser") if align else None
    rep = status.get("repeats") or {}
    rec["repeats"] = _first(rep, "n_runs")
    rec["repeats_success_rate"] = _first(rep, "success_paper_rate", "success_rate")
    regs = rep.get("registered") if isinstance(rep.get("registered"), dict) else {}
    rec["repeats_registered_min"] = _first(regs, "min")
    rec["repeats_registered_max"] = _first(regs, "max")
    return rec


def collect_runs(results: str | Path, gate: GateConfig = GateConfig()) -> pd.DataFrame:
    """Every run of the tree as one DataFrame row (columns :data:`RUN_COLUMNS`)."""
    results = Path(results)
    rows = []
    for run, mode in find_runs(results):
        rows.append(read_run(run, gate, results, mode))
    df = pd.DataFrame(rows, columns=RUN_COLUMNS)
    if len(df):
        # an initialiser-only run (failed: no bridge / training) has no mode; it failed in
        # every mode this initialiser was run with, so it stands for each of them
        parts = []
        for _, g in df.groupby(["dataset", "init"], sort=False):
            modes = sorted(g["bridge_mode"].dropna().unique())
            bare = g[g["bridge_mode"].isna()]
            parts.append(g[g["bridge_mode"].notna()])
            parts += [bare.assign(bridge_mode=m) for m in modes] if modes else [bare]
        df = pd.concat(parts, ignore_index=True).sort_values(
            ["dataset", "scene", "n", "init", "bridge_mode"], na_position="first").reset_index(drop=True)
        # reference cameras are a property of the scene: a failed run (no pose.json) of a scene
        # with references still counts in the gated k/N, as a failure
        scene_ref = df.groupby(["dataset", "scene"])["has_reference"].transform("any").astype(bool)
        unverified = scene_ref & ~df["has_reference"].astype(bool)
        df["has_reference"] = scene_ref
        df.loc[unverified, "success_gated"] = False
    log.info("results: %s under %s (%s, %s)", counted(len(df), "run"), results,
             counted(df["dataset"].nunique(), "dataset"),
             counted(df[["dataset", "scene"]].drop_duplicates().shape[0], "scene"))
    return df
