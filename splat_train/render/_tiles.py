"""Tile binning and a vectorised, device-agnostic tile blender (pure PyTorch, autograd).

:func:`tile_pairs` lists, per 16x16 tile, the Gaussians whose tile rectangle covers it, in
front-to-back order (stable depth sort, ties by index: the same order as the dense reference).
:func:`blend_tiles` blends those lists with padded batched tensor ops; it is the fallback on
devices without the C++ kernel (CUDA without gsplat, or no compiler) and is exact with respect
to :func:`splat_train.render._reference.blend_dense`, with memory bounded by tiles x 256 x list length
per chunk instead of pixels x Gaussians.
"""

from __future__ import annotations

import torch
from torch import Tensor

from splat_train.render._reference import ALPHA_MAX, ALPHA_MIN, T_MIN, depth_order
from splat_train.render.projection import TILE_SIZE, Projected

__all__ = ["tile_pairs", "blend_tiles"]

# Elements (tiles x 256 x slots) per chunk of the vectorised blender.
_CHUNK_ELEMENTS = 1 << 22


def tile_pairs(
    depths: Tensor, rect: Tensor, visible: Tensor, width: int, height: int, tile_size: int = TILE_SIZE
) -> tuple[Tensor, Tensor, int, int]:
    """Tile -> Gaussian intersection lists.

    Args:
        depths: [N] camera z. rect: [N, 4] tile rectangle (x_min, x_max, y_min, y_max),
            max exclusive. visible: [N] bool.
        width, height: image size in pixels.

    Returns:
        offsets [T + 1] int64 (tile t owns pairs offsets[t]:offsets[t + 1], T = tiles_x *
        tiles_y, tile t = ty * tiles_x + tx), gauss [P] int64 Gaussian index per pair
        (front to back within a tile), tiles_x, tiles_y.
    """
    dev = depths.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    with torch.no_grad():
        order = depth_order(depths, visible)
        r = rect[order]
        w = r[:, 1] - r[:, 0]
        h = r[:, 3] - r[:, 2]
        cnt = w * h
        total = int(cnt.sum()) if cnt.numel() else 0
        if total == 0:
            return torch.zeros(n_tiles + 1, dtype=torch.int64, device=dev), torch.zeros(
                0, dtype=torch.int64, device=dev
            ), tiles_x, tiles_y
        rank = torch.repeat_interleave(torch.arange(order.numel(), device=dev), cnt)
        start = torch.cumsum(cnt, 0) - cnt
        local = torch.arange(total, device=dev) - start[rank]
        wr = w[rank]
        tx = r[rank, 0] + local % wr
        ty = r[rank, 2] + torch.div(local, wr, rounding_mode="floor")
        tile = ty * tiles_x + tx
        perm = torch.sort(tile, stable=True).indices
        gauss = order[rank[perm]]
        offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=dev)
        offsets[1:] = torch.cumsum(torch.bincount(tile, minlength=n_tiles), 0)
    return offsets, gauss, tiles_x, tiles_y


def _blend_chunk(tiles, offsets, gauss, means2d, conics, features, opacities, tiles_x, width, height, ts):
    """Blend a chunk of tiles: returns accum [Tc, ts*ts, F] and T_final [Tc, ts*ts]."""
    dev, dt = means2d.device, means2d.dtype
    counts = offsets[tiles + 1] - offsets[tiles]
    slots = int(counts.max())
    slot = torch.arange(slots, device=dev)
    valid = slot[None, :] < counts[:, None]  # [Tc, L]
    pair = (offsets[tiles][:, None] + slot[None, :]).clamp(max=max(gauss.numel() - 1, 0))
    g = torch.where(valid, gauss[pair], torch.zeros_like(pair))  # [Tc, L]
    lp = torch.arange(ts * ts, device=dev)
    px = ((tiles % tiles_x) * ts)[:, None] + lp[None, :] % ts  # [Tc, P]
    py = (torch.div(tiles, tiles_x, rounding_mode="floor") * ts)[:, None] + torch.div(lp, ts, rounding_mode="floor")[None, :]
    m = means2d[g]  # [Tc, L, 2]
    con = conics[g]
    dx = m[:, None, :, 0] - (px.to(dt) + 0.5)[:, :, None]  # [Tc, P, L]
    dy = m[:, None, :, 1] - (py.to(dt) + 0.5)[:, :, None]
    power = -0.5 * (con[:, None, :, 0] * dx * dx + con[:, None, :, 2] * dy * dy) - con[:, None, :, 1] * dx * dy
    ok = valid[:, None, :] & (power <= 0)
    power = torch.where(ok, power, torch.full_like(power, -1e4))
    alpha = torch.clamp_max(opacities[g][:, None, :] * torch.exp(power), ALPHA_MAX)
    alpha = torch.where(ok & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        contributes = torch.cumprod(1.0 - alpha, dim=2) >= T_MIN
    alpha = torch.where(contributes, alpha, torch.zeros_like(alpha))
    trans = torch.cumprod(1.0 - alpha, dim=2)
    t_front = torch.cat([torch.ones_like(trans[..., :1]), trans[..., :-1]], dim=2)
    weights = alpha * t_front  # [Tc, P, L]
    accum = torch.bmm(weights, features[g])  # [Tc, P, F]
    return accum, trans[..., -1]


def blend_tiles(proj: Projected, features: Tensor, opacities: Tensor) -> tuple[Tensor, Tensor]:
    """Vectorised tile blending (autograd); arguments and results as
    :func:`splat_train.render._reference.blend_dense`: ``proj`` the screen-space Gaussians of one image
    (pixels, COLMAP convention), ``features`` [N, F], ``opacities`` [N]; returns accum
    [H, W, F] (no background) and T_final [H, W], rows = image y."""
    means2d, conics = proj.means2d, proj.conics
    width, height, tile_size = proj.width, proj.height, proj.tile_size
    dev, dt = means2d.device, means2d.dtype
    nf = features.shape[1]
    offsets, gauss, tiles_x, tiles_y = tile_pairs(proj.depths, proj.rect, proj.visible, width, height, tile_size)
    n_tiles = tiles_x * tiles_y
    npix = tile_size * tile_size
    counts = offsets[1:] - offsets[:-1]
    order = torch.argsort(counts)
    counts_sorted = counts[order].tolist()
    acc_parts, t_parts, tile_parts = [], [], []
    i = 0
    while i < n_tiles:
        if counts_sorted[i] == 0:
            i += 1
            continue
        # Tiles sorted by list length: grow the chunk while the padded size fits the budget.
        j = i + 1
        while j < n_tiles and (j + 1 - i) * npix * counts_sorted[j] <= _CHUNK_ELEMENTS:
            j += 1
        tiles = order[i:j]
        acc, tf = _blend_chunk(tiles, offsets, gauss, means2d, conics, features, opacities, tiles_x, width, height, tile_size)
        acc_parts.append(acc)
        t_parts.append(tf)
        tile_parts.append(tiles)
        i = j
    accum = torch.zeros(n_tiles, npix, nf, device=dev, dtype=dt) + 0 * features.sum()
    t_final = torch.ones(n_tiles, npix, device=dev, dtype=dt)
    if tile_parts:
        idx = torch.cat(tile_parts)
        accum = accum.index_copy(0, idx, torch.cat(acc_parts))
        t_final = t_final.index_copy(0, idx, torch.cat(t_parts))
    accum = accum.reshape(tiles_y, tiles_x, tile_size, tile_size, nf).permute(0, 2, 1, 3, 4)
    accum = accum.reshape(tiles_y * tile_size, tiles_x * tile_size, nf)[:height, :width]
    t_final = t_final.reshape(tiles_y, tiles_x, tile_size, tile_size).permute(0, 2, 1, 3)
    t_final = t_final.reshape(tiles_y * tile_size, tiles_x * tile_size)[:height, :width]
    return accum, t_final
