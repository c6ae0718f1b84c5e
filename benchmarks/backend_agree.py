"""Do the CPU kernel and gsplat train to the same result? One recipe, seed and cell on both.

The GPU side of the check: the sparse-view grid's own training command
(:func:`experiments.sparse_views.runs.train_and_score`, training only) on one of its prepared cells
with ``--device cuda --rasterizer gsplat``, for each (recipe, seed) of :data:`RUNS` at
:data:`ITERATIONS`; the CPU side is the grid's records of the same cell, recipe, seed and
iterations (``python -m experiments.sparse_views run ... --iterations 3000``, the C++ kernel).
Both are compared on the final iteration of the held-out curve each training writes (PSNR and
SSIM of the model trained on that backend, rendered by it). Called by the GPU check as the part
``backend_agree`` on a copy of the cell (``scripts/gpu_bundle.sh`` makes ``.gpu_agree`` from the
grid's fern n = 3 cell); any backend runs it (the tests use the CPU kernel at a few iterations).
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

__all__ = ["ITERATIONS", "RUNS", "attach_records", "backend_agree", "cell_name", "cell_paths", "curve_end", "pack_cell",
           "parse_runs", "parse_seeds", "split_cell_name"]

# the measure: final held-out PSNR within 0.3 dB at 3,000 iterations
ITERATIONS = 3000
# seed-major, the default recipe first: a run cut short by its deadline keeps whole comparisons
RUNS = (("sparse", 0), ("paper", 0), ("sparse", 1), ("sparse", 2), ("paper", 1), ("paper", 2))


def parse_runs(seeds: str, recipes: str = "sparse,paper") -> tuple[tuple[str, int], ...]:
    """(recipe, seed) pairs, seed-major, from ``seeds`` ("0-14", "0,1,2" or a mix) and a comma
    list of ``recipes`` (the GPU check reads them from ``AGREE_SEEDS`` / ``AGREE_RECIPES``)."""
    from splat_train.recipes import RECIPE_NAMES

    out = parse_seeds(seeds)
    names = [r.strip() for r in recipes.split(",") if r.strip()]
    bad = [r for r in names if r not in RECIPE_NAMES]
    if bad or not names or not out:
        raise ValueError(f"recipes from {list(RECIPE_NAMES)} and at least one seed, got {recipes!r} / {seeds!r}")
    return tuple((r, seed) for seed in out for r in names)


def parse_seeds(text: str) -> list[int]:
    """Seeds from "0-14", "0,1,2" or a mix of them, in order, each once."""
    out: list[int] = []
    for part in filter(None, (x.strip() for x in text.split(","))):
        lo, _, hi = part.partition("-")
        if not lo.isdigit() or (hi and not hi.isdigit()) or (hi and int(hi) < int(lo)):
            raise ValueError(f"seeds are N, N-M or a comma list of them, got {text!r}")
        out += range(int(lo), int(hi or lo) + 1)
    return list(dict.fromkeys(out))


def cell_paths(cell: Path) -> dict[str, Path]:
    """A sparse-view grid cell's paths (experiments/sparse_views/cells.py's layout)."""
    cell = Path(cell)
    paths = {"scene": cell / "scene", "train": cell / "train.txt", "test": cell / "test.txt",
             "bridge": cell / "bridge", "align": cell / "align"}
    missing = [str(p) for p in paths.values() if not p.exists()]
    if missing:
        raise FileNotFoundError(f"{cell} is not a sparse-view grid cell: no {', '.join(missing)}")
    return paths


def cell_name(cell: Path) -> str:
    """A cell folder's grid name: its ``cell.json`` (:func:`pack_cell`), else the folder's name."""
    meta = Path(cell) / "cell.json"
    return json.loads(meta.read_text())["name"] if meta.is_file() else Path(cell).name


def curve_end(rec: dict) -> tuple[int | None, float | None]:
    """(iteration, PSNR) of the last held-out evaluation in a grid record's curve, or Nones."""
    curve = [(i, v) for i, v in zip(*(rec.get("curve", {}).get(k) or [] for k in ("iterations", "psnr")))
             if v is not None]
    return curve[-1] if curve else (None, None)


def _final(tj: dict) -> dict:
    """The last held-out evaluation of a train.json and what ran it."""
    c = tj.get("test_curve") or {}
    return {"psnr": c.get("last_test_psnr"), "ssim": c.get("last_test_ssim"), "at_iteration": c.get("last_iteration"),
            "best_psnr": c.get("best_test_psnr"),
            "gaussians": tj.get("num_gaussians"), "train_s": tj.get("wall_time_s"),
            "backend": tj.get("rasterizer"), "device": tj.get("device")}


def backend_agree(cell: Path, name: str, device: str = "cuda", rasterizer: str = "gsplat",
                  runs=RUNS, iterations: int = ITERATIONS, records: Path | None = None,
                  deadline: float | None = None, run_s: float = 60.0,
                  on_result: Callable[[dict], None] | None = None) -> dict:
    """Train each (recipe, seed) of ``runs`` on ``cell`` with ``device`` / ``rasterizer``, and
    set each beside the grid's record of the same run (``records``: its ``runs`` folder; the
    record of ``<name>_<recipe>_s<seed>_i<iterations>``) where one exists.

    Args:
        cell: a grid cell folder (:func:`cell_paths`); name: its grid name (``llff__fern_n3``).
        deadline: a ``time.time()`` value; no run starts later than ``run_s`` before it.
        on_result: called with the result after each run (the live dict: write it out at once).

    Returns:
        dict: ``cell``, ``iterations``, ``device``, ``rasterizer``; ``runs``: one entry per run
        (``recipe``, ``seed``, ``this``: :func:`_final` of this backend, ``record``: the same of the
        grid's record or None, ``psnr_diff``: this minus the record, dB); ``by_recipe``: the mean
        final PSNR of each backend over the seeds both have and the mean difference, and
        ``all_records``: these runs against every grid record of the recipe, unpaired
        (:func:`_against_all_records`); ``stopped_at_deadline``.
    """
    from experiments.sparse_views.runs import train_and_score

    paths = cell_paths(cell)
    split_cell_name(name)  # a bad name fails before any training
    eval_every = max(1, iterations // 10)  # the grid's default period
    res = {"cell": name, "iterations": iterations, "device": device, "rasterizer": rasterizer, "runs": [],
           "by_recipe": {}, "stopped_at_deadline": False}
    with tempfile.TemporaryDirectory(prefix="backend_agree_") as tmp:
        for recipe, seed in runs:
            if deadline is not None and time.time() + run_s > deadline:
                res["stopped_at_deadline"] = True
                break
            t0 = time.perf_counter()
            out = train_and_score(paths, Path(tmp) / f"{recipe}_s{seed}", recipe, seed, iterations, eval_every,
                                  extra_args=("--device", device, "--rasterizer", rasterizer), score=False)
            entry = {"recipe": recipe, "seed": seed, "this": _final(out["train"]), "record": None,
                     "psnr_diff": None, "run_s": time.perf_counter() - t0}
            res["runs"].append(entry)
            if records is not None:
                attach_records(res, records)
            if on_result is not None:
                on_result(res)
    return res


def attach_records(res: dict, records: Path) -> dict:
    """Set each run of a :func:`backend_agree` result beside the grid's record of the same cell,
    recipe, seed and iterations in ``records`` (its ``runs`` folder), where one exists
    (``record``, ``psnr_diff``), and recompute ``by_recipe``; ``res`` is updated and returned.
    The GPU runs may come before the CPU records: ``python -m benchmarks.backend_agree compare``
    attaches them afterwards."""
    from experiments.sparse_views.runs import run_name

    for entry in res["runs"]:
        entry["record"], entry["psnr_diff"] = None, None
        rec_path = Path(records) / f"{run_name(*split_cell_name(res['cell']), entry['recipe'], entry['seed'], res['iterations'])}.json"
        if not rec_path.is_file():
            continue
        rec = json.loads(rec_path.read_text())
        at, psnr = curve_end(rec)
        entry["record"] = {"psnr": psnr, "at_iteration": at,
                           "scored_psnr": rec.get("psnr"), "gaussians": rec.get("gaussians"),
                           "train_s": rec.get("train_s"), "backend": rec.get("backend"), "path": rec_path.name}
        if entry["this"]["psnr"] is not None and entry["record"]["psnr"] is not None:
            entry["psnr_diff"] = entry["this"]["psnr"] - entry["record"]["psnr"]
    res["by_recipe"] = _by_recipe(res["runs"])
    for recipe, b in res["by_recipe"].items():
        b["all_records"] = _against_all_records(res, recipe, Path(records))
    return res


def _against_all_records(res: dict, recipe: str, records: Path) -> dict | None:
    """This backend's runs of ``recipe`` against every grid record of the same cell, recipe and
    iterations, whatever their seeds (unpaired): ``seeds``, ``mean``, ``sd``, and the
    difference with Welch's 95 % half-width (:func:`evaluation.study.stats.welch_interval`)."""
    from experiments.sparse_views.runs import run_name
    from evaluation.study.stats import welch_interval

    scene, n = split_cell_name(res["cell"])
    pattern = run_name(scene, n, recipe, 0, res["iterations"]).replace("_s0_", "_s*_")
    recs = [json.loads(p.read_text()) for p in sorted(Path(records).glob(pattern + ".json"))]
    vals = [v for v in (curve_end(r)[1] for r in recs if r.get("recipe") == recipe) if v is not None]
    this = [r["this"]["psnr"] for r in res["runs"] if r["recipe"] == recipe and r["this"]["psnr"] is not None]
    if len(vals) < 2 or not this:
        return None
    diff, hw, df = welch_interval(this, vals)
    return {"seeds": len(vals), "mean": statistics.mean(vals), "sd": statistics.stdev(vals),
            "this_seeds": len(this), "psnr_diff": diff, "psnr_diff_hw95": None if hw != hw else hw, "df": df}


def split_cell_name(name: str) -> tuple[str, int]:
    """The scene and view count of a grid cell name (``llff__fern_n3`` -> ``("llff__fern", 3)``)."""
    head, _, n = name.rpartition("_n")
    if not head or not n.isdigit():
        raise ValueError(f"a grid cell name is <scene>_n<views>, got {name!r}")
    return head, int(n)


def _by_recipe(runs: list[dict]) -> dict:
    """Per recipe, over the seeds both backends ran: mean final PSNR of each, the mean paired
    difference with its 95 % t half-width (None below two seeds), the largest seed's |diff|,
    and each backend's seed-to-seed standard deviation."""
    from evaluation.study.stats import t_interval

    out = {}
    for recipe in dict.fromkeys(r["recipe"] for r in runs):
        both = [r for r in runs if r["recipe"] == recipe and r["psnr_diff"] is not None]
        if not both:
            continue
        mean, hw, _k = t_interval([r["psnr_diff"] for r in both])
        sd = (lambda xs: statistics.stdev(xs) if len(xs) > 1 else None)
        out[recipe] = {"seeds": [r["seed"] for r in both],
                       "this_psnr": statistics.mean(r["this"]["psnr"] for r in both),
                       "record_psnr": statistics.mean(r["record"]["psnr"] for r in both),
                       "psnr_diff": mean, "psnr_diff_hw95": None if hw != hw else hw,
                       "max_abs_seed_diff": max(abs(r["psnr_diff"]) for r in both),
                       "this_seed_sd": sd([r["this"]["psnr"] for r in both]),
                       "record_seed_sd": sd([r["record"]["psnr"] for r in both])}
    return out


def pack_cell(dest: Path, scene: str = "llff__fern", n: int = 3, work: Path | None = None,
              data: Path | None = None, protocol_file: Path | None = None) -> Path:
    """Prepare the grid cell of ``scene`` at ``n`` views in ``work`` (kept files are reused) and
    copy what training reads into the folder ``dest`` (scene, bridge, align, train.txt,
    test.txt, each replacing its earlier copy whole: an entry is never half-written), with ``cell.json`` naming it; the GPU
    check carries it (scripts/gpu_bundle.sh: ``.gpu_agree``). The command line checks ``dest``
    against the output rule first (:func:`main`)."""
    from experiments.sparse_views import protocol
    from experiments.sparse_views.cells import prepare
    from runtime.atomic import atomic_dir, atomic_path, write_json

    protocol_file = protocol_file or protocol.PROTOCOL
    found = [s for s in protocol.load(protocol_file, data) if s.name == scene]
    if not found:
        raise ValueError(f"no scene {scene!r} in {protocol_file}")
    if not found[0].available:
        raise FileNotFoundError(f"{scene}: its data is not at {found[0].path}")
    name = f"{scene}_n{n}"
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        paths = prepare(Path(work) / name if work is not None else Path(tmp) / name, found[0], n)
        for key in ("scene", "bridge", "align"):
            with atomic_dir(dest / key) as d:
                shutil.copytree(paths[key], d, dirs_exist_ok=True)
        for key in ("train", "test"):
            with atomic_path(dest / f"{key}.txt") as f:
                shutil.copyfile(paths[key], f)
    write_json(dest / "cell.json", {"name": name, "scene": scene, "n": n})
    return dest


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.backend_agree pack DEST``: pack a grid cell for the GPU check;
    ``... compare RESULT.json``: set a GPU check's backend_agree runs beside the grid's records."""
    p = argparse.ArgumentParser(description="The GPU check's backend comparison: pack a grid cell for it, or set "
                                            "its runs beside the grid's CPU records")
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("compare", help="attach the grid's records to the backend_agree part of a GPU check's "
                                       "JSON (or of a record) and print the comparison")
    c.add_argument("result", type=Path, help="benchmarks_gpu_*.json or benchmarks/records/gpu-*.json")
    c.add_argument("--records", type=Path, default=Path(__file__).resolve().parents[1] / "experiments" / "records" / "sparse_views" / "runs",
                   help="the grid's runs folder (default %(default)s)")
    c.add_argument("--write", action="store_true", help="write the updated part back into RESULT")
    k = sub.add_parser("pack", help="prepare a grid cell and copy what training reads")
    k.add_argument("dest", type=Path, help="folder to write (replaced whole)")
    k.add_argument("--scene", default="llff__fern", help="a scene of the grid's protocol (default %(default)s)")
    k.add_argument("--n", type=int, default=3, help="training views (default %(default)s)")
    k.add_argument("--work", type=Path, default=None, help="the grid's --work folder, whose cell is reused")
    k.add_argument("--data", type=Path, default=None, help="the grid's --data folder")
    k.add_argument("--protocol", type=Path, default=None, help="the grid's scenes file (default: its own)")
    args = p.parse_args(argv)
    if args.command == "compare":
        return _compare_cli(args)
    import logging

    from runtime.outdir import prepare_out, run_stage, seal_out
    from runtime.logs import setup_logging

    setup_logging()
    stage = "backend_agree pack"

    def work() -> None:
        # the folder is this command's alone: never an input, nor a folder another command wrote
        prepare_out(args.dest, {"--work": args.work, "--data": args.data, "--protocol": args.protocol}, stage,
                    replaces=True)
        out = pack_cell(args.dest, args.scene, args.n, args.work, args.data, args.protocol)
        seal_out(out, stage)
        print(f"backend_agree: packed {args.scene} n = {args.n} into {out}")

    return run_stage(logging.getLogger("benchmarks.backend_agree"), work)


def _compare_cli(args) -> int:
    from runtime.atomic import write_json

    try:
        doc = json.loads(args.result.read_text())
        part = doc["backend_agree"]
        part["runs"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"error: {args.result} holds no backend_agree part with runs ({exc})", file=sys.stderr)
        return 2
    attach_records(part, args.records)
    for r in part["runs"]:
        rec = r["record"]
        print(f"{r['recipe']:8s} seed {r['seed']}: {part['rasterizer']} {r['this']['psnr']:.2f} dB"
              + (f", {rec['backend']} {rec['psnr']:.2f} dB, diff {r['psnr_diff']:+.2f}" if rec else ", no record"))
    for recipe, b in part["by_recipe"].items():
        hw = "" if b["psnr_diff_hw95"] is None else f" ± {b['psnr_diff_hw95']:.2f}"
        print(f"{recipe:8s} seeds {b['seeds']}: {b['this_psnr']:.2f} vs {b['record_psnr']:.2f} dB, "
              f"diff {b['psnr_diff']:+.2f}{hw} (95 % t, paired)")
        a = b.get("all_records")
        if a:
            hw = "" if a["psnr_diff_hw95"] is None else f" ± {a['psnr_diff_hw95']:.2f}"
            print(f"{recipe:8s} against all {a['seeds']} records (mean {a['mean']:.2f}, sd {a['sd']:.2f}): "
                  f"diff {a['psnr_diff']:+.2f}{hw} (95 %, Welch)")
    if args.write:
        write_json(args.result, doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
