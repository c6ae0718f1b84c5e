"""Floater measure against a known surface (scenes with ground-truth geometry).

Definition (the one place; docs/reference.md section 6 cites it):

    floater_frac = sum_i alpha_i [d_i > tau] / sum_i alpha_i

* i runs over the Gaussians of a model (seed.ply or the trained model.ply), alpha_i =
  sigmoid(opacity logit), the opacity each Gaussian was given (unitless, in (0, 1));
* d_i = distance from the Gaussian's centre, mapped into the reference (ground-truth) frame by
  the run's Sim(3) (align.json: x_ref = scale R x_model + t, fitted on the training cameras),
  to the ground-truth surface: the exact point-to-triangle distance to the synthetic scene's
  mesh (rebuilt from the seed in ``synthetic.json``; open3d ``compute_distance``), in
  reference-frame scene units;
* tau = ``tau_rel`` * r_ref, r_ref = RMS distance of all reference camera centres from their
  mean (the scene's trajectory radius, scene units); ``tau_rel`` defaults to
  :data:`TAU_REL`.

So floater_frac is the fraction of the opacity mass (unitless, 0..1) that sits farther than
tau from the true surface. Sky: the synthetic scene's background has no surface; Gaussians
seeded on background rays (the oracle puts them at the far depth) count as floaters when they
are farther than tau from every surface. Also written: the opacity mass (sum alpha_i),
the number of Gaussians and the opacity-weighted mean of min(d_i, 10 tau) / tau.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from runtime.atomic import write_json
from camio.colmap import read_model
from camio.ply import read_gaussian_ply
from evaluation.metrics.align import Sim3

__all__ = ["TAU_REL", "floater_fraction", "surface_distance", "trajectory_radius", "run_floaters"]

log = logging.getLogger(__name__)

TAU_REL = 0.05  # tau as a fraction of the reference trajectory radius (the one default)


def trajectory_radius(centres: np.ndarray) -> float:
    """RMS distance of camera centres [C, 3] from their mean (scene units)."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=1))))


def floater_fraction(dist: np.ndarray, alpha: np.ndarray, tau: float) -> dict:
    """The floater measure of the module docstring, from the distances.

    Args:
        dist: [N] distance of each Gaussian centre to the ground-truth surface (scene units).
        alpha: [N] opacities in [0, 1].
        tau: distance threshold (scene units, > 0).

    Returns:
        {"floater_frac" (0..1; NaN when the opacity mass is 0), "opacity_mass", "n_gaussians",
        "mean_dist_over_tau" (opacity-weighted mean of min(d, 10 tau) / tau), "tau"}.
    """
    d = np.asarray(dist, np.float64).reshape(-1)
    alpha = np.asarray(alpha, np.float64).reshape(-1)
    if len(alpha) != len(d):
        raise ValueError(f"alpha has {len(alpha)} entries for {len(d)} distances")
    if not tau > 0:
        raise ValueError(f"tau must be > 0, got {tau}")
    mass = float(alpha.sum())
    if len(d) == 0 or mass <= 0:
        return {"floater_frac": float("nan"), "opacity_mass": mass, "n_gaussians": len(d),
                "mean_dist_over_tau": float("nan"), "tau": float(tau)}
    return {"floater_frac": float(alpha[d > tau].sum() / mass), "opacity_mass": mass,
            "n_gaussians": int(len(d)),
            "mean_dist_over_tau": float(np.sum(alpha * np.minimum(d, 10 * tau)) / mass / tau),
            "tau": float(tau)}


def surface_distance(scene: str | Path, points_ref: np.ndarray) -> np.ndarray:
    """Distance [N] of points [N, 3] (reference frame) to the synthetic scene's exact mesh.

    The mesh is rebuilt with :func:`camio.synthetic.build_scene` from the ``seed`` recorded
    in ``scene/synthetic.json`` (FileNotFoundError for a scene without one).
    """
    import open3d as o3d

    from camio.synthetic import build_scene

    info = Path(scene) / "synthetic.json"
    if not info.is_file():
        raise FileNotFoundError(f"{info} is missing: the floater measure needs a synthetic scene "
                                "(python -m camio synth), whose surface is known exactly")
    mesh = build_scene(int(json.loads(info.read_text())["seed"]))
    pts = np.asarray(points_ref, np.float32).reshape(-1, 3)
    return mesh.raycaster.compute_distance(o3d.core.Tensor(pts)).numpy().astype(np.float64)


def read_align(path: str | Path) -> Sim3:
    """The model-to-reference Sim(3) of an align.json (``scale``, ``R`` [3, 3], ``t`` [3]).

    Raises:
        ValueError: one line naming the file: not JSON, a field missing or of the wrong shape,
            or a value that is not finite (a NaN scale makes every distance NaN).
    """
    try:
        rec = json.loads(Path(path).read_bytes())
        scale, R, t = (np.asarray(rec[k], np.float64) for k in ("scale", "R", "t"))
        shapes_ok = scale.shape == () and R.shape == (3, 3) and t.shape == (3,)
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path} is not an align.json ({type(exc).__name__}: {exc}); write it with "
                         "`python -m evaluation align`") from None
    if not shapes_ok or not (np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite(scale) and scale > 0):
        raise ValueError(f"{path}: scale must be a finite number > 0, R 3x3 and t 3 finite numbers; write it "
                         "again with `python -m evaluation align`")
    return Sim3(float(scale), R, t)


def run_floaters(models: dict[str, str | Path], align: str | Path, scene: str | Path,
                 out: str | Path, tau_rel: float | None = None) -> dict:
    """Floater measure of each model (name -> PLY in the run's model frame) -> ``out`` JSON.

    Args:
        models: e.g. {"seed": bridge/seed.ply, "final": train/model.ply}.
        align: align.json of the run (model frame -> reference frame).
        scene: prepared synthetic scene (``sparse/0`` reference cameras, ``synthetic.json``).
        out: JSON to write: {"tau_rel", "tau", "r_ref", <name>: floater_fraction(...)}.
        tau_rel: threshold / r_ref (None: :data:`TAU_REL`).
    """
    tau_rel = TAU_REL if tau_rel is None else float(tau_rel)
    scene = Path(scene)
    ref = read_model(scene / "sparse" / "0")
    r_ref = trajectory_radius(np.stack([ref.camera(n).center for n in ref.names]))
    tau = tau_rel * r_ref
    sim = read_align(align)
    result = {"tau_rel": float(tau_rel), "tau": tau, "r_ref": r_ref,
              "definition": "opacity-weighted fraction of Gaussians farther than tau from the GT mesh"}
    for name, path in models.items():
        cloud = read_gaussian_ply(path)
        dist = surface_distance(scene, sim.apply(cloud.means))
        result[name] = floater_fraction(dist, cloud.opacity, tau)
        log.info("floaters %s: %.4f of the opacity mass farther than %.4g from the surface (%d Gaussians)",
                 name, result[name]["floater_frac"], tau, len(cloud))
    write_json(out, result)
    return result
