"""Pose accuracy of an initialiser's cameras against reference cameras,
and the accuracy-gated success (docs/contracts.md).

Definitions (cameras matched by image name; ``R_i, t_i`` = cam_from_world of camera i):

* ATE: RMS of the camera-centre errors after the Sim(3) alignment prediction -> reference
  (:func:`evaluation.metrics.align.fit_sim3_cameras`), in reference units; ``ate_rel_radius`` = ATE /
  RMS trajectory radius (RMS distance of the reference centres from their mean), a fraction
  (``ate_pct_radius`` is the same in percent).
* RPE over all camera pairs i < j (alignment-free; relative poses do not depend on the frame):
  the rotation error is the angle of ``(R_i R_j^T)_pred^T (R_i R_j^T)_ref``; the translation
  direction error is the angle between the directions of ``t_ij = t_i - R_i R_j^T t_j``
  (pairs with zero baseline on either side are skipped). ``rpe_rot_deg`` and
  ``rpe_trans_dir_deg`` are means, ``*_max_deg`` maxima; ``rel_rot_err_mean_deg`` /
  ``rel_rot_err_max_deg`` (the accuracy gate's names) are the same rotation numbers.
* ``fy_fx_*``: fy / fx of the predicted PINHOLE cameras (1 for SIMPLE_PINHOLE); a drift away
  from 1 flags a bad model.
* Success: the two criteria of docs/contracts.md ("Success"), side by side under the same
  names in status.json, pose.json, the tables and the report: ``success_paper`` (>= 1
  registered image and >= 1 point, :func:`paper_success`) and ``success_gated`` (paper
  success, >= 3 registered training views for the Sim(3) step, ate_rel_radius <
  ``max_ate_rel_radius`` (:data:`MAX_ATE_REL_RADIUS`, 0.05) and rel_rot_err_mean_deg <
  ``max_rel_rot_deg`` (:data:`MAX_REL_ROT_DEG`, 5);
  :func:`accuracy_gate`; None where there are no reference cameras).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

from camio.colmap import SparseModel
from evaluation.metrics.align import (COLLINEAR_TOL, AlignmentError, fit_sim3_cameras,
                                      rotation_angle_deg)
from runtime.checks import flag

__all__ = ["MAX_ATE_REL_RADIUS", "MAX_REL_ROT_DEG", "GateConfig", "add_gate_args", "gate_from_args", "relative_pose_errors", "paper_success", "status_success", "accuracy_gate",
           "success_criteria_text", "evaluate_pose",
           "run_pose", "focal_ratio_stats"]

log = logging.getLogger(__name__)


#: The accuracy gate's defaults, defined here only: every CLI flag default and help text reads
#: them; config.yaml and the workflow schema repeat the values, and a test checks they agree.
MAX_ATE_REL_RADIUS = 0.05  # ATE / RMS trajectory radius (a fraction)
MAX_REL_ROT_DEG = 5.0  # mean relative rotation error, degrees


@dataclass(frozen=True)
class GateConfig:
    """Thresholds of the accuracy gate."""

    max_ate_rel_radius: float = MAX_ATE_REL_RADIUS
    max_rel_rot_deg: float = MAX_REL_ROT_DEG
    min_aligned_views: int = 3


def add_gate_args(parser, what: str = "accuracy gate") -> None:
    """Add ``--max-ate-rel-radius`` and ``--max-rel-rot-deg`` (defaults: the constants above)
    to an argparse parser; :func:`gate_from_args` reads them back."""
    parser.add_argument("--max-ate-rel-radius", type=flag(float, 0, lo_open=True), default=MAX_ATE_REL_RADIUS,
                        help=f"{what}: ATE / RMS trajectory radius must be below this "
                             f"(default {MAX_ATE_REL_RADIUS:g})")
    parser.add_argument("--max-rel-rot-deg", type=flag(float, 0, lo_open=True), default=MAX_REL_ROT_DEG,
                        help=f"{what}: mean relative rotation error must be below this "
                             f"(default {MAX_REL_ROT_DEG:g})")


def gate_from_args(args) -> GateConfig:
    """The :class:`GateConfig` of parsed :func:`add_gate_args` flags."""
    return GateConfig(max_ate_rel_radius=args.max_ate_rel_radius, max_rel_rot_deg=args.max_rel_rot_deg)


def relative_pose_errors(pred_cfw: np.ndarray, ref_cfw: np.ndarray) -> dict:
    """Alignment-free relative rotation and translation-direction errors over all pairs.

    Args:
        pred_cfw: [N, 3|4, 4] predicted cam_from_world (any frame).
        ref_cfw: [N, 3|4, 4] reference cam_from_world, same camera order.

    Returns:
        ``rot_deg`` [P] and ``trans_dir_deg`` [P] (NaN where a baseline is zero) over the
        P = N (N - 1) / 2 pairs, and ``pairs`` [P, 2].
    """
    p = np.asarray(pred_cfw, np.float64)[:, :3]
    r = np.asarray(ref_cfw, np.float64)[:, :3]
    pairs = np.array(list(combinations(range(len(p)), 2)), dtype=np.int64).reshape(-1, 2)
    if len(pairs) == 0:
        return {"rot_deg": np.zeros(0), "trans_dir_deg": np.zeros(0), "pairs": pairs}
    i, j = pairs[:, 0], pairs[:, 1]

    def rel(m):
        rr = m[i, :, :3] @ np.swapaxes(m[j, :, :3], 1, 2)  # cam_i from cam_j
        tt = m[i, :, 3] - np.einsum("pab,pb->pa", rr, m[j, :, 3])
        return rr, tt

    rp, tp = rel(p)
    rr, tr = rel(r)
    rot = rotation_angle_deg(np.swapaxes(rp, 1, 2) @ rr)
    np_, nr = np.linalg.norm(tp, axis=1), np.linalg.norm(tr, axis=1)
    scale = max(float(np.max(nr)), float(np.max(np_)), 1e-300)
    ok = (np_ > 1e-12 * scale) & (nr > 1e-12 * scale)
    trans = np.full(len(pairs), np.nan)
    cross = np.linalg.norm(np.cross(tp[ok], tr[ok]), axis=1)
    dot = np.sum(tp[ok] * tr[ok], axis=1)
    trans[ok] = np.degrees(np.arctan2(cross, dot))
    return {"rot_deg": rot, "trans_dir_deg": trans, "pairs": pairs}


def focal_ratio_stats(model: SparseModel, names: list[str] | None = None) -> dict:
    """fy / fx of the model's cameras (those named): mean, min, max and max |ratio - 1|."""
    ratios = [c.K[1, 1] / c.K[0, 0] for c in model.cameras if names is None or c.name in names]
    if not ratios:
        return {"fy_fx_mean": None, "fy_fx_min": None, "fy_fx_max": None, "fy_fx_max_dev": None}
    a = np.asarray(ratios)
    return {"fy_fx_mean": float(a.mean()), "fy_fx_min": float(a.min()), "fy_fx_max": float(a.max()),
            "fy_fx_max_dev": float(np.max(np.abs(a - 1.0)))}


def paper_success(n_registered: int, n_points: int) -> bool:
    """``success_paper`` (docs/contracts.md): >= 1 registered image and >= 1 point."""
    return bool(n_registered >= 1 and n_points >= 1)


def status_success(status: dict) -> bool:
    """``success_paper`` of a status.json (``success`` in files written before the rename)."""
    return bool(status.get("success_paper", status.get("success", False)))


def success_criteria_text(gate: "GateConfig" = None, html: bool = False) -> list[str]:
    """The two criteria in words, for the tables and the report (one wording everywhere)."""
    gate = gate or GateConfig()
    lt = "&lt;" if html else "<"
    return ["Success (paper), success_paper: a model with >= 1 registered image and >= 1 point.",
            f"Success (accurate), success_gated (the accuracy gate): paper success, >= {gate.min_aligned_views} registered "
            f"training views (for the Sim(3) alignment), ATE {lt} {100 * gate.max_ate_rel_radius:g}% of the "
            f"RMS trajectory radius and mean relative rotation error {lt} {gate.max_rel_rot_deg:g} deg "
            "(scenes with reference cameras only)."]


def accuracy_gate(record: dict, gate: GateConfig = GateConfig()) -> bool | None:
    """Accuracy-gated success from a pose record (keys of :func:`evaluate_pose`).

    Returns None when the scene has no reference cameras (``has_reference`` false): the gate
    does not apply; else False when the paper criterion fails or a figure is missing.
    """
    if not record.get("has_reference", True):
        return None
    if not record.get("success_paper", False):
        return False
    reg = record.get("registered")
    if reg is not None and reg < gate.min_aligned_views:
        return False
    ate = record.get("ate_rel_radius")
    rot = record.get("rel_rot_err_mean_deg")
    if ate is None or rot is None or not (np.isfinite(ate) and np.isfinite(rot)):
        return False
    return bool(ate < gate.max_ate_rel_radius and rot < gate.max_rel_rot_deg)


def _nanstat(fn, a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(fn(a)) if len(a) else None


def evaluate_pose(pred: SparseModel, ref: SparseModel, names: list[str] | None = None,
                  gate: GateConfig = GateConfig(), use_orientations: str = "auto",
                  collinear_tol: float = COLLINEAR_TOL) -> dict:
    """Pose accuracy of ``pred`` against ``ref`` (see the module docstring for every key).

    Args:
        pred: the initialiser's model (any frame).
        ref: the reference model.
        names: restrict to these image names (e.g. the training views); the expected count
            ``n_names`` (registered / n) is their number. None: every reference name.
        gate: accuracy-gate thresholds.

    Returns:
        The pose.json record.
    """
    expected = sorted(set(names)) if names is not None else sorted(ref.names)
    pred_names = set(pred.names)
    matched = [n for n in expected if n in pred_names and n in ref.names]
    registered = sorted(n for n in expected if n in pred_names)
    rec: dict = {
        "n_names": len(expected), "n_pred": len(pred.cameras), "n_ref": len(ref.cameras),
        "n_matched": len(matched), "registered": len(registered),
        "registered_fraction": len(registered) / len(expected) if expected else None,
        "n_points": int(len(pred.points)), "names_matched": matched,
        "names_missing": [n for n in expected if n not in matched],
        "camera_models": sorted({m for m, _ in pred.camera_models.values()}),
        "has_reference": True,
        **focal_ratio_stats(pred, matched),
        "gate": asdict(gate),
    }
    keys = ("ate_rmse", "ate_rel_radius", "ate_pct_radius", "trajectory_radius", "rpe_rot_deg",
            "rpe_rot_max_deg", "rpe_trans_dir_deg", "rpe_trans_dir_max_deg", "rel_rot_err_mean_deg",
            "rel_rot_err_max_deg", "alignment")
    rec.update({k: None for k in keys})
    if len(matched) >= 2:
        pc = np.stack([pred.camera(n).cam_from_world for n in matched])
        rc = np.stack([ref.camera(n).cam_from_world for n in matched])
        rel = relative_pose_errors(pc, rc)
        rec.update({
            "rpe_rot_deg": _nanstat(np.mean, rel["rot_deg"]), "rpe_rot_max_deg": _nanstat(np.max, rel["rot_deg"]),
            "rpe_trans_dir_deg": _nanstat(np.mean, rel["trans_dir_deg"]),
            "rpe_trans_dir_max_deg": _nanstat(np.max, rel["trans_dir_deg"]),
        })
        rec["rel_rot_err_mean_deg"] = rec["rpe_rot_deg"]
        rec["rel_rot_err_max_deg"] = rec["rpe_rot_max_deg"]
    if len(matched) >= gate.min_aligned_views:
        try:
            al = fit_sim3_cameras({n: pred.camera(n).cam_from_world for n in matched},
                                  {n: ref.camera(n).cam_from_world for n in matched},
                                  use_orientations=use_orientations, collinear_tol=collinear_tol,
                                  min_cameras=gate.min_aligned_views)
        except AlignmentError as exc:
            log.warning("pose: no alignment: %s", exc)
            rec["alignment_error"] = str(exc)
        else:
            rel_r = al.rmse / al.ref_radius
            rec.update({"ate_rmse": al.rmse, "ate_rel_radius": rel_r, "ate_pct_radius": 100 * rel_r,
                        "trajectory_radius": al.ref_radius, "alignment": al.to_json()})
    rec["success_paper"] = paper_success(len(registered), len(pred.points))
    rec["success_gated"] = accuracy_gate(rec, gate)
    return rec


def run_pose(pred_dir: str | Path, ref_dir: str | Path, out: str | Path,
             names_file: str | Path | None = None, n: int | None = None,
             gate: GateConfig = GateConfig(), use_orientations: str = "auto") -> dict:
    """Read two COLMAP models, evaluate, write ``pose.json`` atomically; returns the record."""
    from runtime.atomic import write_json
    from camio.colmap import read_model
    from evaluation.metrics.align_run import load_names

    t0 = time.perf_counter()
    # poses only: a distorted camera model's distortion does not matter here
    pred = read_model(pred_dir, allow_distorted=True)
    ref = read_model(ref_dir, allow_distorted=True)
    names = None
    if names_file is not None:
        names = load_names(names_file, "train", n, available=pred.names)
    rec = evaluate_pose(pred, ref, names, gate, use_orientations)
    rec.update({"pred": str(pred_dir), "ref": str(ref_dir), "wall_time_s": time.perf_counter() - t0})
    write_json(out, rec)
    fmt = lambda v, f="{:.3g}": "n/a" if v is None else f.format(v)  # noqa: E731
    log.info("pose: %d/%d matched, ATE %s (%s%% of radius), RPE rot %s deg, trans dir %s deg, "
             "success paper=%s gated=%s -> %s in %.2f s", rec["n_matched"], rec["n_names"],
             fmt(rec["ate_rmse"]), fmt(rec["ate_pct_radius"]), fmt(rec["rpe_rot_deg"]),
             fmt(rec["rpe_trans_dir_deg"]), rec["success_paper"], rec["success_gated"], out,
             rec["wall_time_s"])
    return rec
