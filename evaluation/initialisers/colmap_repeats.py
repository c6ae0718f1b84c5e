"""Repeated, seeded runs of the COLMAP baseline and the spread of their results.

``run_colmap_repeats`` runs :func:`evaluation.initialisers.colmap_run.run_colmap` once per seed,
optionally evaluates each run against reference cameras (ATE, relative rotation error, the
paper's and the accuracy-gated success through :func:`evaluation.metrics.pose.evaluate_pose`) and
reports the spread. CLI: ``python -m evaluation.initialisers.colmap_baseline --repeats K [--ref MODEL]``.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_dir, write_json
from evaluation.initialisers.colmap_run import ColmapSettings, run_colmap
from evaluation.metrics.pose import status_success

__all__ = ["summarise_repeats", "run_colmap_repeats"]

log = logging.getLogger(__name__)


def summarise_repeats(records: list[dict]) -> dict:
    """The spread over repeated runs: registered counts, points, success rates, and (when
    the runs were evaluated against reference cameras) ATE and the accuracy-gated success.

    Args:
        records: status records of runs with different seeds (with ``pose`` where evaluated).

    Returns:
        ``seeds``, ``registered`` (values, min, max, mean, std), ``points`` (same),
        ``success_paper_rate``, ``aligned_ok_rate``, ``n_runs``; with poses also
        ``ate_rel_radius`` (values, None where no alignment; min/max/mean/std over the others),
        ``rel_rot_err_mean_deg`` (same) and ``success_gated_rate``.
    """
    def spread(values: list) -> dict:
        v = np.array([x for x in values if x is not None], dtype=np.float64)
        out = {"values": values}
        out.update({"min": float(v.min()), "max": float(v.max()), "mean": float(v.mean()),
                    "std": float(v.std())} if len(v) else
                   {"min": None, "max": None, "mean": None, "std": None})
        return out

    summary = {
        "n_runs": len(records),
        "seeds": [r["seed"] for r in records],
        "registered": spread([int(r["registered"]) for r in records]),
        "points": spread([int(r["points"]) for r in records]),
        "success_paper_rate": float(np.mean([status_success(r) for r in records])),
        "aligned_ok_rate": float(np.mean([r["aligned_ok"] for r in records])),
        "wall_time_s": [r["wall_time_s"] for r in records],
    }
    if any("pose" in r for r in records):
        poses = [r.get("pose") or {} for r in records]
        summary["ate_rel_radius"] = spread([p.get("ate_rel_radius") for p in poses])
        summary["rel_rot_err_mean_deg"] = spread([p.get("rel_rot_err_mean_deg") for p in poses])
        summary["success_gated_rate"] = float(np.mean([bool(p.get("success_gated")) for p in poses]))
    return summary


def _pose_of_run(run_dir: Path, ref_dir: Path, names: list[str], gate) -> dict | None:
    """Pose figures of one run against the reference cameras (None without a model)."""
    from camio.colmap import read_model
    from evaluation.metrics.pose import evaluate_pose

    if not (run_dir / "sparse" / "0").is_dir():
        return {"success_paper": False, "success_gated": False, "ate_rel_radius": None,
                "rel_rot_err_mean_deg": None}
    rec = evaluate_pose(read_model(run_dir / "sparse" / "0"), read_model(ref_dir), names, gate)
    keys = ("ate_rel_radius", "rel_rot_err_mean_deg", "rel_rot_err_max_deg", "success_paper",
            "success_gated", "registered")
    return {k: rec.get(k) for k in keys}


def run_colmap_repeats(images_dir: str | Path, names: list[str], out_dir: str | Path,
                       seeds: list[int], settings: ColmapSettings | None = None,
                       ref: str | Path | None = None, gate=None) -> dict:
    """Run the baseline once per seed; the first seed's run is the primary result.

    Each run goes to ``out_dir/repeats/seed<s>``; the first seed's model and status are
    also written to ``out_dir`` itself (the contract every other stage reads), with the
    spread over all runs under ``status["repeats"]``.

    Args:
        ref: reference COLMAP model; if given every run is evaluated with
            :func:`evaluation.metrics.pose.evaluate_pose` (ATE, relative rotation error, both success
            criteria) and the spread of those figures is reported too.
        gate: :class:`evaluation.metrics.pose.GateConfig` thresholds (its defaults if None).

    Returns:
        The primary status record with ``repeats`` added.
    """
    if not seeds:
        raise ValueError("run_colmap_repeats: give at least one seed")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"run_colmap_repeats: seeds must be distinct, got {seeds}")
    out_dir = Path(out_dir)
    records = []
    for i, seed in enumerate(seeds):
        log.info("COLMAP repeat %d/%d (seed %d)", i + 1, len(seeds), seed)
        run_dir = out_dir / "repeats" / f"seed{seed}"
        rec = run_colmap(images_dir, names, run_dir, seed=seed, settings=settings)
        if ref is not None:
            from evaluation.metrics.pose import GateConfig

            rec["pose"] = _pose_of_run(run_dir, Path(ref), names, gate or GateConfig())
            write_json(run_dir / "status.json", rec)
        records.append(rec)
    first = out_dir / "repeats" / f"seed{seeds[0]}"
    primary = dict(records[0])
    if (first / "sparse" / "0").is_dir():
        with atomic_dir(out_dir / "sparse" / "0") as tmp:
            for f in (first / "sparse" / "0").iterdir():
                shutil.copy2(f, tmp / f.name)
    elif (out_dir / "sparse" / "0").exists():
        shutil.rmtree(out_dir / "sparse" / "0")
    primary["repeats"] = summarise_repeats(records)
    write_json(out_dir / "status.json", primary)
    rep = primary["repeats"]
    log.info("COLMAP repeats: registered %s, success rate %.2f, aligned rate %.2f%s",
             rep["registered"]["values"], rep["success_paper_rate"], rep["aligned_ok_rate"],
             f", gated rate {rep['success_gated_rate']:.2f}, ATE/radius "
             f"{rep['ate_rel_radius']['values']}" if "success_gated_rate" in rep else "")
    return primary


if __name__ == "__main__":
    import sys

    from runtime.cliargs import not_a_command

    sys.exit(not_a_command("evaluation.initialisers.colmap_repeats", "python -m evaluation.initialisers.colmap_baseline --repeats N"))
