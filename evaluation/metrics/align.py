"""Sim(3) alignment of an initialiser's cameras to the reference cameras.

Convention: a :class:`Sim3` maps points of a *source* frame into a *target* frame,
``x_target = s * R @ x_source + t``. For evaluation the source is the initialiser's
(prediction's, trained model's) frame and the target is the reference frame.

The fit is Umeyama's closed-form least-squares similarity with the reflection guard, on the
training-camera centres matched by image name. Camera centres that are (nearly) collinear --
common at n = 3, where three views lie on a shallow arc -- leave the rotation about their line
undetermined, so the fit then also uses the camera orientations: beside each centre ``C`` it
places the three points ``C + r * a_k`` along the camera's x, y, z axes (``a_k`` = row k of
the camera's ``R``), with ``r`` the RMS trajectory radius of that frame. Since a similarity maps
the prediction's radius to the reference radius and camera axes by ``R``, these points are
related by the same similarity, so noise-free cameras give the exact similarity even for two
cameras or three on a line. Coincident centres leave the scale undetermined: an error.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from camio.cameras import camera_center, rotmat_to_qvec, to_homogeneous

__all__ = [
    "Sim3",
    "AlignmentError",
    "Alignment",
    "umeyama",
    "collinearity_ratio",
    "rms_radius",
    "fit_sim3_cameras",
    "transform_cam_from_world",
    "rotation_angle_deg",
    "COLLINEAR_TOL",
]

log = logging.getLogger(__name__)

#: collinearity ratio (sigma2 / sigma1 of the camera centres) below which they count as collinear
#: and the Sim(3) fit uses the camera orientations too (``use_orientations="auto"``)
COLLINEAR_TOL = 0.1


class AlignmentError(ValueError):
    """Cameras from which no similarity can be fitted (too few, coincident, non-finite)."""


@dataclass(frozen=True)
class Sim3:
    """A similarity ``x_target = s * R @ x_source + t``.

    Attributes:
        s: scale (> 0).
        R: [3, 3] rotation (det +1).
        t: [3] translation (target units).
    """

    s: float
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "s", float(self.s))
        object.__setattr__(self, "R", np.asarray(self.R, np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, np.float64).reshape(3))
        if not self.s > 0:
            raise ValueError(f"Sim3 scale must be positive, got {self.s}")

    @staticmethod
    def identity() -> "Sim3":
        return Sim3(1.0, np.eye(3), np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map source points [..., 3] to target points [..., 3]."""
        p = np.asarray(points, np.float64)
        return self.s * p @ self.R.T + self.t

    def inverse(self) -> "Sim3":
        """The similarity target -> source."""
        return Sim3(1.0 / self.s, self.R.T, -self.R.T @ self.t / self.s)

    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous matrix [[s R, t], [0, 1]]."""
        m = np.eye(4)
        m[:3, :3] = self.s * self.R
        m[:3, 3] = self.t
        return m

    def to_json(self) -> dict:
        return {"scale": self.s, "R": self.R.tolist(), "t": self.t.tolist(),
                "qvec_wxyz": rotmat_to_qvec(self.R).tolist(),
                "direction": "x_target = scale * R @ x_source + t"}


def umeyama(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> Sim3:
    """Least-squares similarity with ``dst ~ s R src + t`` (Umeyama 1991, reflection guarded).

    Args:
        src: [N, 3] source points.
        dst: [N, 3] target points (row i corresponds to src row i).
        weights: [N] non-negative weights, or None for equal weights.

    Returns:
        The similarity source -> target.

    Raises:
        AlignmentError: shapes differ, fewer than 2 points, non-finite input, or the source
            points coincide (scale undetermined).
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise AlignmentError(f"umeyama: src and dst must both be [N, 3], got {src.shape} and {dst.shape}")
    if len(src) < 2:
        raise AlignmentError(f"umeyama: need at least 2 point pairs, got {len(src)}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise AlignmentError("umeyama: non-finite coordinates")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d
    var_s = float(w @ np.sum(xs * xs, axis=1))
    if var_s <= 1e-24 * max(1.0, float(np.max(np.abs(src)))) ** 2:
        raise AlignmentError("umeyama: the source points coincide; the scale is undetermined")
    cov = (xd * w[:, None]).T @ xs  # [3, 3] = sum_i w_i xd_i xs_i^T
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # reflection guard
        sign[2, 2] = -1.0
    rot = u @ sign @ vt
    scale = float(np.sum(d * np.diag(sign)) / var_s)
    if not scale > 0:
        raise AlignmentError(f"umeyama: degenerate fit (scale {scale:.3g}); the points are not "
                             "related by a similarity")
    return Sim3(scale, rot, mu_d - scale * rot @ mu_s)


def rms_radius(centres: np.ndarray) -> float:
    """RMS distance of points [N, 3] from their mean (the RMS trajectory radius)."""
    c = np.asarray(centres, np.float64)
    return float(np.sqrt(np.mean(np.sum((c - c.mean(axis=0)) ** 2, axis=1))))


def collinearity_ratio(centres: np.ndarray) -> float:
    """sigma_2 / sigma_1 of the centred points [N, 3]: 0 on a line, ~1 for a round cloud.

    Returns 0.0 for fewer than 3 points or coincident points.
    """
    c = np.asarray(centres, np.float64)
    if len(c) < 3:
        return 0.0
    sv = np.linalg.svd(c - c.mean(axis=0), compute_uv=False)
    return float(sv[1] / sv[0]) if sv[0] > 0 else 0.0


def rotation_angle_deg(rot: np.ndarray) -> np.ndarray:
    """Angle of rotation matrices [..., 3, 3] in degrees, [...]; accurate near 0 and 180."""
    r = np.asarray(rot, np.float64)
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    vee = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                    r[..., 1, 0] - r[..., 0, 1]], axis=-1)
    sin = np.linalg.norm(vee, axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))


@dataclass
class Alignment:
    """A fitted prediction -> reference similarity and how well it fits.

    Attributes:
        sim: the similarity (source = prediction frame, target = reference frame).
        names: the image names used, sorted.
        centre_residuals: [N] distances |sim(C_pred) - C_ref| in reference units.
        rotation_residuals_deg: [N] angles between the aligned and the reference camera
            orientations.
        rmse: RMS of ``centre_residuals`` (the ATE).
        ref_radius: RMS trajectory radius of the reference centres.
        collinearity: min over both frames of :func:`collinearity_ratio`.
        collinear: ``collinearity < collinear_tol``.
        used_orientations: whether the camera axes entered the fit.
    """

    sim: Sim3
    names: list[str]
    centre_residuals: np.ndarray
    rotation_residuals_deg: np.ndarray
    rmse: float
    ref_radius: float
    collinearity: float
    collinear: bool
    used_orientations: bool
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            **self.sim.to_json(),
            "names": self.names,
            "n_cameras": len(self.names),
            "centre_residuals": dict(zip(self.names, self.centre_residuals.tolist())),
            "rotation_residuals_deg": dict(zip(self.names, self.rotation_residuals_deg.tolist())),
            "rmse": self.rmse,
            "ref_radius": self.ref_radius,
            "rmse_rel_radius": self.rmse / self.ref_radius if self.ref_radius > 0 else None,
            "collinearity": self.collinearity,
            "collinear": self.collinear,
            "used_orientations": self.used_orientations,
            **self.extra,
        }


def _axis_points(cfw: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """[N, 3, 3] points C + radius * (camera axis k in world) for k = x, y, z."""
    return centres[:, None, :] + radius * cfw[:, :3, :3]


def fit_sim3_cameras(
    pred: dict[str, np.ndarray],
    ref: dict[str, np.ndarray],
    names: list[str] | None = None,
    use_orientations: str = "auto",
    collinear_tol: float = COLLINEAR_TOL,
    min_cameras: int = 3,
    coincident_tol: float = 1e-9,
) -> Alignment:
    """Fit the similarity prediction -> reference on matched training cameras.

    Args:
        pred: image name -> cam_from_world [3|4, 4] in the prediction frame.
        ref: image name -> cam_from_world [3|4, 4] in the reference frame.
        names: names to use (default: every name in both); names missing from either side
            are skipped with a warning.
        use_orientations: "auto" (add camera-axis points only when the centres are nearly
            collinear), "always" or "never" (centres only, as the paper's protocol).
        collinear_tol: the ``collinearity_ratio`` below which centres count as collinear.
        min_cameras: fewer matched cameras is an error (the protocol needs 3).
        coincident_tol: centres whose RMS radius is below ``coincident_tol * max(1, max|C|)``
            in either frame count as coincident: an error.

    Returns:
        The :class:`Alignment`.

    Raises:
        AlignmentError: too few matched cameras, coincident centres or non-finite poses.
    """
    if use_orientations not in ("auto", "always", "never"):
        raise ValueError(f"use_orientations must be 'auto', 'always' or 'never', got {use_orientations!r}")
    wanted = sorted(set(pred) & set(ref)) if names is None else sorted(set(names))
    missing = [n for n in wanted if n not in pred or n not in ref]
    if missing:
        log.warning("alignment: %d of %d cameras are missing from the prediction or the "
                    "reference and are skipped: %s", len(missing), len(wanted), missing[:5])
    used = [n for n in wanted if n in pred and n in ref]
    if len(used) < min_cameras:
        raise AlignmentError(f"Sim(3) alignment needs at least {min_cameras} cameras present in both "
                             f"models, found {len(used)} ({used}); the run cannot be aligned")
    cp = np.stack([to_homogeneous(pred[n])[:3] for n in used])
    cr = np.stack([to_homogeneous(ref[n])[:3] for n in used])
    if not (np.all(np.isfinite(cp)) and np.all(np.isfinite(cr))):
        raise AlignmentError("Sim(3) alignment: non-finite camera poses")
    c_pred, c_ref = camera_center(cp), camera_center(cr)
    r_pred, r_ref = rms_radius(c_pred), rms_radius(c_ref)
    for label, c, r in (("prediction", c_pred, r_pred), ("reference", c_ref, r_ref)):
        if r <= coincident_tol * max(1.0, float(np.max(np.abs(c)))):
            raise AlignmentError(
                f"the {label}'s camera centres coincide (RMS radius {r:.3g}): the similarity's "
                "scale is undetermined (a pure-rotation capture?); the run cannot be aligned")
    ratio = min(collinearity_ratio(c_pred), collinearity_ratio(c_ref))
    collinear = ratio < collinear_tol
    with_axes = use_orientations == "always" or (use_orientations == "auto" and collinear)
    if collinear:
        log.warning("alignment: the %d camera centres are nearly collinear (sigma2/sigma1 = %.3g "
                    "< %.3g); %s", len(used), ratio, collinear_tol,
                    "using the camera orientations too" if with_axes else
                    "the rotation about their line is poorly determined")
    if with_axes:
        src = np.concatenate([c_pred, _axis_points(cp, c_pred, r_pred).reshape(-1, 3)])
        dst = np.concatenate([c_ref, _axis_points(cr, c_ref, r_ref).reshape(-1, 3)])
    else:
        src, dst = c_pred, c_ref
    sim = umeyama(src, dst)
    res = np.linalg.norm(sim.apply(c_pred) - c_ref, axis=1)
    # aligned orientation: world_from_cam' = R world_from_cam -> cam_from_world' = R_c R^T
    rot_res = rotation_angle_deg(np.einsum("nij,kj->nik", cp[:, :, :3], sim.R)
                                 @ np.swapaxes(cr[:, :, :3], 1, 2))
    rmse = float(np.sqrt(np.mean(res ** 2)))
    log.info("Sim(3) on %d cameras: scale %.4g, ATE %.4g (%.2f%% of radius %.4g), collinearity %.3g%s",
             len(used), sim.s, rmse, 100 * rmse / r_ref, r_ref, ratio,
             " (orientations used)" if with_axes else "")
    return Alignment(sim, used, res, rot_res, rmse, r_ref, ratio, collinear, with_axes)


def transform_cam_from_world(cam_from_world: np.ndarray, sim: Sim3) -> np.ndarray:
    """The same physical camera expressed in the similarity's target frame.

    With ``x_B = s R x_A + t`` and a camera ``x_cam = R_c x_A + t_c`` in frame A, the camera
    in frame B is ``[R_c R^T | s t_c - R_c R^T t]`` (its camera frame scaled by s, which leaves
    every projection unchanged).

    Args:
        cam_from_world: [..., 3|4, 4] extrinsics in the source frame A.
        sim: the similarity A -> B.

    Returns:
        [..., 3, 4] extrinsics in frame B.
    """
    m = to_homogeneous(cam_from_world)
    rc = m[..., :3, :3]
    tc = m[..., :3, 3]
    rn = rc @ sim.R.T
    tn = sim.s * tc - np.einsum("...ij,j->...i", rn, sim.t)
    return np.concatenate([rn, tn[..., None]], axis=-1)
