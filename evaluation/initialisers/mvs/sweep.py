"""Plane-sweep stereo for one reference view over its source views, on the CPU in torch.

For every reference pixel and every depth hypothesis (fronto-parallel planes of the reference
camera, spaced uniformly in inverse depth rho = 1/z), each source image is warped onto the
reference by the plane's homography and compared with the reference over a square window by
normalised cross-correlation (NCC) of grey values. The matching cost of a source is 1 - NCC in
[0, 2]; the cost of a hypothesis is the mean of the ``top_k`` lowest source costs (a source
that cannot see the pixel, or sees it occluded, does not drag the others down). The depth is
the hypothesis of least cost, refined by a parabola through its neighbours in rho; the
matching confidence is :func:`matching_confidence` of the best NCC and its margin over the
best hypothesis outside its neighbourhood.

Frames and pixels (camio): cameras are cam_from_world, OpenCV axes; a pixel (row i, column j)
has its centre at (j + 0.5, i + 0.5), which is what ``K`` maps to, and grid_sample with
``align_corners=False`` uses the same continuous coordinates (u / W * 2 - 1).

Memory: the cost volume is [D, H, W] float32 (D hypotheses at the working resolution); the
warps are made ``chunk`` hypotheses at a time, [chunk, H, W] per buffer, so memory is
O(D H W + chunk H W) whatever the number of sources.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["SweepResult", "relative_pose", "ray_grid", "box_mean", "ncc_costs", "plane_sweep",
           "matching_confidence", "inverse_depth_planes"]

#: cost of a hypothesis a source cannot see (1 - NCC of uncorrelated windows is 1; 2 is the worst)
INVALID_COST = 2.0


@dataclass
class SweepResult:
    """One reference view's sweep.

    Attributes:
        depth: [H, W] float32 z-depth in the reference camera (NaN where no hypothesis was valid
            or the reference window has no texture).
        score: [H, W] float32 best NCC in [-1, 1] (aggregated over the ``top_k`` best sources).
        margin: [H, W] float32 second-best cost (outside the best's neighbourhood) minus the best.
        conf: [H, W] float32 matching confidence in [0, 1] (:func:`matching_confidence`).
        textureless: [H, W] bool, reference windows whose grey-level standard deviation is below
            the threshold (no depth is estimated there).
    """

    depth: np.ndarray
    score: np.ndarray
    margin: np.ndarray
    conf: np.ndarray
    textureless: np.ndarray


def relative_pose(ref_cfw: np.ndarray, src_cfw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Source-from-reference rotation [3, 3] and translation [3] (float64) of two cam_from_world."""
    R_r, t_r = ref_cfw[:3, :3], ref_cfw[:3, 3]
    R_s, t_s = src_cfw[:3, :3], src_cfw[:3, 3]
    R = R_s @ R_r.T
    return R, t_s - R @ t_r


def ray_grid(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rays K^-1 [u, v, 1] of every pixel centre, [3, H*W] float64 (z = 1, row-major pixels)."""
    u = np.arange(width, dtype=np.float64) + 0.5
    v = np.arange(height, dtype=np.float64) + 0.5
    uu, vv = np.meshgrid(u, v)
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    return np.linalg.solve(K, pix)


def inverse_depth_planes(rho_min: float, rho_max: float, count: int) -> np.ndarray:
    """``count`` inverse depths from ``rho_max`` (near) down to ``rho_min`` (far), evenly
    spaced, [count] float64; ``rho_min`` may be 0 (a plane at infinity)."""
    if not (np.isfinite(rho_min) and np.isfinite(rho_max)) or rho_min < 0 or rho_max <= rho_min:
        raise ValueError(f"inverse depth bounds must satisfy 0 <= min < max, got [{rho_min}, {rho_max}]")
    if count < 2:
        raise ValueError(f"need >= 2 depth hypotheses, got {count}")
    return np.linspace(rho_max, rho_min, int(count))


def box_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window`` x ``window`` square around every pixel of [B, H, W] (border
    windows count only their pixels inside the image; a NaN in a window gives NaN), [B, H, W].
    Separable: a row pass, then a column pass."""
    pad = window // 2
    y = F.avg_pool2d(x.unsqueeze(1), (1, window), stride=1, padding=(0, pad), count_include_pad=False)
    return F.avg_pool2d(y, (window, 1), stride=1, padding=(pad, 0), count_include_pad=False).squeeze(1)


def ncc_costs(ref: torch.Tensor, ref_mean: torch.Tensor, ref_std: torch.Tensor, warped: torch.Tensor,
              window: int, eps: float = 1e-6) -> torch.Tensor:
    """1 - NCC of the reference against warped source images, [B, H, W] in [0, 2].

    Args:
        ref: [H, W] reference grey image.
        ref_mean, ref_std: [H, W] its window mean and standard deviation (:func:`box_mean`).
        warped: [B, H, W] the source warped by B hypotheses, NaN where the warp fell outside
            the source image.
        window: odd window size.

    Returns:
        Cost per hypothesis; :data:`INVALID_COST` where any pixel of the window fell outside
        the source image or the warped window has no texture.
    """
    B = warped.shape[0]
    stats = box_mean(torch.cat([warped, warped * warped, warped * ref]), window)
    mj, mjj, mij = stats[:B], stats[B:2 * B], stats[2 * B:]
    var_j = (mjj - mj * mj).clamp_min(0)
    cov = mij - ref_mean * mj
    ncc = cov / (ref_std * var_j.sqrt() + eps)
    cost = 1.0 - ncc.clamp(-1.0, 1.0)
    bad = torch.isnan(cost) | (var_j < eps)
    return torch.where(bad, torch.full_like(cost, INVALID_COST), cost)


def matching_confidence(score: np.ndarray, margin: np.ndarray, margin_scale: float) -> np.ndarray:
    """Confidence of a match in [0, 1]: max(NCC, 0) * (1 - exp(-margin / margin_scale)).

    A match is trusted when the windows correlate well (NCC near 1) and no other depth along
    the ray correlates nearly as well (a large margin: repeated texture and uniform regions
    have none). NaN inputs give 0.
    """
    s = np.clip(np.nan_to_num(score, nan=0.0), 0.0, 1.0)
    m = np.clip(np.nan_to_num(margin, nan=0.0), 0.0, None)
    return (s * (1.0 - np.exp(-m / margin_scale))).astype(np.float32)


def _sweep_family(ref, ref_mean, ref_std, src_data, rays, normal, sigma_range, rhos, H, W, window, k,
                  exclusion, chunk):
    """One family of parallel planes n . X = 1 / sigma (``normal`` n in the reference frame,
    ``sigma_range`` the span of sigma, None for the fronto-parallel planes at ``rhos``): per
    pixel the best cost, its refined inverse depth and the second-best cost (all [H, W])."""
    D = len(rhos)
    nx = torch.from_numpy(np.asarray(normal, np.float64) @ rays)  # [HW], n . x of every ray
    facing = nx > 1e-3
    rho_lo, rho_hi = float(min(rhos)), float(max(rhos))
    if not facing.any():
        inf = torch.full((H, W), INVALID_COST, dtype=torch.float32)
        return inf, torch.zeros((H, W), dtype=torch.float64), inf
    if sigma_range is None:  # fronto-parallel: sigma is the inverse depth itself
        sigmas = torch.from_numpy(np.asarray(rhos, np.float64))
    else:
        sigmas = torch.linspace(max(sigma_range), min(sigma_range), D, dtype=torch.float64)
    volume = torch.empty((D, H, W), dtype=torch.float32)
    for start in range(0, D, chunk):
        rho = (sigmas[start:start + chunk, None] * nx[None]).float()  # [B, HW] per-pixel inverse depth
        B = rho.shape[0]
        usable = facing[None] & (rho >= rho_lo * (1 - 1e-5)) & (rho <= rho_hi * (1 + 1e-5))
        costs = []
        for A, b, img, ws, hs in src_data:
            uvw = A[None] + rho[:, None, :] * b[None, :, None]  # [B, 3, HW]
            z = uvw[:, 2]
            ok = (z > 1e-12) & usable
            zs = torch.where(ok, z, torch.ones_like(z))
            u, v = uvw[:, 0] / zs, uvw[:, 1] / zs
            inside = ok & (u >= 0) & (u <= ws) & (v >= 0) & (v <= hs)
            u = torch.where(inside, u, torch.zeros_like(u))
            v = torch.where(inside, v, torch.zeros_like(v))
            grid = torch.stack([u / ws * 2 - 1, v / hs * 2 - 1], -1).reshape(B, H, W, 2)
            warped = F.grid_sample(img.expand(B, -1, -1, -1), grid, mode="bilinear",
                                   padding_mode="border", align_corners=False)[:, 0]
            warped = torch.where(inside.reshape(B, H, W), warped, torch.full_like(warped, np.nan))
            costs.append(ncc_costs(ref, ref_mean, ref_std, warped, window))
        stack = torch.stack(costs)  # [S, B, H, W]
        if k < len(costs):
            stack = torch.topk(stack, k, dim=0, largest=False).values
        volume[start:start + B] = stack.mean(0)
    best_cost, best = volume.min(0)
    idx = torch.arange(D)[:, None, None]
    second = torch.where((idx - best[None]).abs() > exclusion, volume,
                         torch.full_like(volume, np.inf)).min(0).values
    # parabola through the best and its neighbours (in sigma), clipped to half a step
    lo = volume.gather(0, (best - 1).clamp_min(0)[None])[0]
    hi = volume.gather(0, (best + 1).clamp_max(D - 1)[None])[0]
    curv = lo - 2 * best_cost + hi
    interior = (best > 0) & (best < D - 1) & (curv > 1e-9) & (lo < INVALID_COST) & (hi < INVALID_COST)
    offset = torch.where(interior, 0.5 * (lo - hi) / curv.clamp_min(1e-9), torch.zeros_like(curv)).clamp(-0.5, 0.5)
    step = float(sigmas[1] - sigmas[0])
    rho = (sigmas[best] + offset.double() * step) * nx.reshape(H, W)
    return best_cost, rho, second


def plane_sweep(ref_gray: np.ndarray, ref_K: np.ndarray, ref_cfw: np.ndarray,
                sources: list[tuple[np.ndarray, np.ndarray, np.ndarray]], rhos: np.ndarray, *,
                window: int, min_std: float, margin_scale: float, chunk: int,
                normals: list[tuple[np.ndarray, tuple[float, float]]] = (), top_k: int = 1,
                exclusion: int = 2) -> SweepResult:
    """Depth of every pixel of a reference view by a plane sweep (module docstring).

    Args:
        ref_gray: [H, W] float32 grey reference image in [0, 1].
        ref_K: [3, 3] reference intrinsics at [H, W] (COLMAP pixel centres).
        ref_cfw: [3, 4] reference cam_from_world (OpenCV axes).
        sources: per source view (grey [Hs, Ws] float32, K [3, 3], cam_from_world [3, 4]).
        rhos: [D] inverse depths of the fronto-parallel planes, near to far
            (:func:`inverse_depth_planes`); every family sweeps D planes within these bounds.
        normals: further plane families, each (unit normal [3] in the *world* frame, (sigma_lo,
            sigma_hi)): the planes n_c . X_c = 1 / sigma of the reference camera, n_c the normal
            turned into its frame and to face it, sigma spanning the range given
            (:func:`evaluation.initialisers.mvs.bounds.plane_family_range`). A scene's dominant
            planes (a ground, a wall) match as the windows warp with their slant (multiple
            sweep directions, Gallup et al. CVPR 2007); each pixel keeps the family of least cost.
        window: NCC window (odd); window, min_std, margin_scale and chunk have their defaults in
            :class:`evaluation.initialisers.mvs.run.MvsConfig`, whose values the caller passes.
        top_k: sources averaged per hypothesis (the k lowest costs).
        min_std: grey-level standard deviation below which a reference window is textureless.
        margin_scale: the margin at which :func:`matching_confidence` reaches 1 - 1/e.
        exclusion: hypotheses either side of the best left out of the second-best cost.
        chunk: hypotheses warped at once (memory, module docstring).

    Returns:
        :class:`SweepResult` at the reference's resolution.
    """
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    if not sources:
        raise ValueError("plane_sweep: no source views")
    H, W = ref_gray.shape
    k = max(1, min(int(top_k), len(sources)))
    ref = torch.from_numpy(np.ascontiguousarray(ref_gray, np.float32))
    ref_mean = box_mean(ref[None], window)[0]
    ref_std = (box_mean((ref * ref)[None], window)[0] - ref_mean ** 2).clamp_min(0).sqrt()
    textureless = ref_std < min_std
    rays = ray_grid(ref_K, W, H)  # [3, HW]
    # per source: A = K_s R rays, b = K_s t; a pixel at inverse depth rho maps to A + rho b
    src_data = []
    for gray, K, cfw in sources:
        R, t = relative_pose(ref_cfw, cfw)
        A = torch.from_numpy(K @ R @ rays).float()  # [3, HW]
        b = torch.from_numpy(K @ t).float()  # [3]
        img = torch.from_numpy(np.ascontiguousarray(gray, np.float32))[None, None]
        src_data.append((A, b, img, gray.shape[1], gray.shape[0]))
    families = [(np.array([0.0, 0.0, 1.0]), None)]
    for n, span in normals:
        n_cam = ref_cfw[:3, :3] @ (np.asarray(n, np.float64) / np.linalg.norm(n))
        families.append((n_cam, span))
    best_cost = second = rho = None
    for normal, span in families:
        c, r_, s_ = _sweep_family(ref, ref_mean, ref_std, src_data, rays, normal, span, rhos, H, W, window, k,
                                  exclusion, chunk)
        if best_cost is None:
            best_cost, rho, second = c, r_, s_
        else:
            better = c < best_cost
            best_cost = torch.where(better, c, best_cost)
            rho = torch.where(better, r_, rho)
            second = torch.where(better, s_, second)
    valid = (best_cost < INVALID_COST - 1e-6) & ~textureless & (rho > 0)
    depth = torch.where(valid, 1.0 / rho.clamp_min(1e-300), torch.full_like(rho, np.nan)).float().numpy()
    score = torch.where(valid, 1.0 - best_cost, torch.full_like(best_cost, np.nan)).numpy()
    margin = torch.where(valid & torch.isfinite(second), second - best_cost,
                         torch.zeros_like(best_cost)).numpy()
    conf = np.where(valid.numpy(), matching_confidence(score, margin, margin_scale), 0.0).astype(np.float32)
    return SweepResult(depth, score.astype(np.float32), margin.astype(np.float32), conf, textureless.numpy())
