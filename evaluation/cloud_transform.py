"""Move a Gaussian cloud through a similarity (the model into the reference frame).

``x' = s R x + t`` maps every Gaussian: means ``s R mu + t``; rotations ``q_R * q`` (so the
covariance becomes ``s^2 R Sigma R^T``); log scales ``+ log s``; opacity unchanged. The
view-dependent colour must also turn with the scene: a view direction ``d`` becomes ``R d``,
so each SH band ``l >= 1`` is multiplied by a [2l+1, 2l+1] matrix ``M_l`` chosen so that the
colour seen along ``R d`` after the move equals the colour seen along ``d`` before. ``M_l`` is
computed by least squares over sampled directions in the 3DGS real SH basis (exact to float64
round-off; checked in the tests).
"""

from __future__ import annotations

import numpy as np

from camio.cameras import rotmat_to_qvec
from camio.ply import GaussianCloud
from evaluation.align import Sim3

__all__ = ["sh_basis", "sh_rotation_matrices", "quat_multiply", "transform_cloud", "eval_sh_color"]

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
       0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: np.ndarray, degree: int = 3) -> np.ndarray:
    """Real SH basis of 3DGS (its ``eval_sh`` order and signs) at unit directions.

    Args:
        dirs: [M, 3] unit view directions (world frame, from camera to Gaussian).
        degree: 0..3.

    Returns:
        [M, (degree + 1)^2] basis values.
    """
    d = np.asarray(dirs, np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    cols = [np.full_like(x, _C0)]
    if degree >= 1:
        cols += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        cols += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy), _C2[3] * x * z,
                 _C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
                 _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                 _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    if degree > 3 or degree < 0:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return np.stack(cols, axis=1)


def eval_sh_color(cloud: GaussianCloud, dirs: np.ndarray) -> np.ndarray:
    """Colour (before the +0.5 offset and clamping) of each Gaussian seen along ``dirs``.

    Args:
        cloud: N Gaussians.
        dirs: [N, 3] unit directions from the camera centre to each Gaussian (world frame).

    Returns:
        [N, 3] float64 ``sum_k c_k Y_k(d)``.
    """
    deg = cloud.sh_degree
    basis = sh_basis(dirs, deg)  # [N, K]
    coeffs = np.concatenate([cloud.sh_dc[:, None, :], cloud.sh_rest], axis=1).astype(np.float64)
    return np.einsum("nk,nkc->nc", basis, coeffs)


def sh_rotation_matrices(rot: np.ndarray, degree: int = 3, n_samples: int = 256,
                         seed: int = 0) -> list[np.ndarray]:
    """Per-band matrices M_l ([2l+1, 2l+1], l = 1..degree) with
    ``sum_k c'_k Y_k(R d) = sum_k c_k Y_k(d)`` for ``c' = M_l c`` (band l).

    Args:
        rot: [3, 3] rotation R of the scene (view directions turn as d -> R d).
        degree: highest SH degree.
    """
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n_samples, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    y = sh_basis(d, degree)  # Y(d)
    y_rot = sh_basis(d @ np.asarray(rot, np.float64).T, degree)  # Y(R d)
    out = []
    for band in range(1, degree + 1):
        sl = slice(band * band, (band + 1) * (band + 1))
        # want Y(R d) . c' = Y(d) . c  <=>  c' = lstsq(Y(R d), Y(d)) c
        m, *_ = np.linalg.lstsq(y_rot[:, sl], y[:, sl], rcond=None)
        out.append(m)
    return out


def quat_multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions, broadcasting [..., 4] x [..., 4]."""
    w1, x1, y1, z1 = np.moveaxis(np.asarray(q1, np.float64), -1, 0)
    w2, x2, y2, z2 = np.moveaxis(np.asarray(q2, np.float64), -1, 0)
    return np.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], axis=-1)


def transform_cloud(cloud: GaussianCloud, sim: Sim3) -> GaussianCloud:
    """The cloud moved by ``sim`` (source frame -> target frame); see the module docstring.

    Args:
        cloud: N Gaussians in the source frame.
        sim: the similarity.

    Returns:
        A new cloud in the target frame (float32 storage as in the PLY).
    """
    means = sim.apply(cloud.means.astype(np.float64))
    quats = quat_multiply(rotmat_to_qvec(sim.R), cloud.quats.astype(np.float64))
    rest = cloud.sh_rest.astype(np.float64).copy()
    for band, m in enumerate(sh_rotation_matrices(sim.R, cloud.sh_degree), start=1):
        sl = slice(band * band - 1, (band + 1) * (band + 1) - 1)  # sh_rest omits the DC term
        rest[:, sl] = np.einsum("ij,njc->nic", m, rest[:, sl])
    return GaussianCloud(
        means=means,
        sh_dc=cloud.sh_dc.copy(),
        sh_rest=rest,
        opacity_logit=cloud.opacity_logit.copy(),
        log_scales=cloud.log_scales.astype(np.float64) + np.log(sim.s),
        quats=quats,
    )
