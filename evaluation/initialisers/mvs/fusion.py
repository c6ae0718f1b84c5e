"""Geometric consistency of the per-view depth maps, and their fusion into one point set.

A pixel p of view r with depth z is unprojected to X and projected into every other view j
(pixel q, depth z_j). View j *agrees* when its own depth at q, unprojected and projected back
into r, lands within ``tol_px`` of p at a depth within ``tol_rel`` of z (the forward-backward
check of COLMAP's fusion and of MVSNet's filter). View j *sees* the point when q is in the image,
j has a depth there, and that depth is not in front of z_j by more than ``tol_rel`` (then j
sees something nearer: X is occluded in j, which neither confirms nor contradicts it). The
geometric confidence is agreeing / seeing; a pixel is kept when at least ``min_agree`` views
agree. Fusion averages each kept pixel with its agreeing pixels and, walking the views in
order, drops a pixel that an earlier view's kept pixel already took (one point per surface
patch), with a COLMAP track of the views that agreed.

Frames: cam_from_world, OpenCV axes; pixels in camio's convention (centres at +0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Consistency", "unproject", "project", "check_consistency", "FusedPoints", "fuse"]


def unproject(depth: np.ndarray, K: np.ndarray, cfw: np.ndarray) -> np.ndarray:
    """World points [H, W, 3] float64 of every pixel centre at z-depth ``depth`` [H, W]
    (:func:`evaluation.initialisers.oracle.unproject_depth` over the whole grid)."""
    from evaluation.initialisers.oracle import unproject_depth

    H, W = depth.shape
    return unproject_depth(depth, K, cfw, np.arange(H), np.arange(W))


def project(points: np.ndarray, K: np.ndarray, cfw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels [..., 2] and z [...] of world points [..., 3] (NaN pixels where z <= 0):
    :func:`camio.cameras.project_points` for any leading shape."""
    from camio.cameras import project_points

    shape = np.shape(points)[:-1]
    uv, z = project_points(np.reshape(points, (-1, 3)), K, cfw)
    return uv.reshape(*shape, 2), z.reshape(shape)


@dataclass
class Consistency:
    """Per view, from :func:`check_consistency`.

    Attributes:
        agree: [H, W] int, views that agree with the pixel.
        sees: [H, W] int, views that see it (agreeing ones included).
        points: [H, W, 3] float64 the pixel's own point (NaN without depth).
        fused: [H, W, 3] float64 mean of its own point and the agreeing views' points.
        matches: per other view j, ([H, W] bool agree, [H, W] int flat pixel index of q in j).
    """

    agree: np.ndarray
    sees: np.ndarray
    points: np.ndarray
    fused: np.ndarray
    matches: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


def check_consistency(depths: list[np.ndarray], Ks: list[np.ndarray], cfws: list[np.ndarray],
                      tol_px: float = 1.0, tol_rel: float = 0.01) -> list[Consistency]:
    """The forward-backward check of every view against every other (module docstring).

    Args:
        depths: per view [H, W] z-depth (NaN where none); all views share [H, W].
        Ks: per view [3, 3] intrinsics at [H, W].
        cfws: per view [3, 4] cam_from_world.
        tol_px: reprojection tolerance, pixels.
        tol_rel: relative depth tolerance.
    """
    S = len(depths)
    pts = [unproject(np.nan_to_num(d, nan=0.0), K, c) for d, K, c in zip(depths, Ks, cfws)]
    for d, p in zip(depths, pts):
        p[~np.isfinite(d)] = np.nan
    out = []
    for r in range(S):
        H, W = depths[r].shape
        has = np.isfinite(depths[r])
        agree = np.zeros((H, W), np.int32)
        sees = np.zeros((H, W), np.int32)
        acc = np.where(has[..., None], pts[r], 0.0)
        u0, v0 = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        matches = {}
        for j in range(S):
            if j == r:
                continue
            Hj, Wj = depths[j].shape
            uv, z = project(pts[r], Ks[j], cfws[j])
            with np.errstate(invalid="ignore"):
                col, row = np.floor(uv[..., 0]), np.floor(uv[..., 1])
                inside = has & (col >= 0) & (col < Wj) & (row >= 0) & (row < Hj)
            ci = np.where(inside, col, 0).astype(np.int64)
            ri = np.where(inside, row, 0).astype(np.int64)
            dj = np.where(inside, depths[j][ri, ci], np.nan)
            xj = pts[j][ri, ci]  # [H, W, 3]
            back, zb = project(xj, Ks[r], cfws[r])
            with np.errstate(invalid="ignore"):
                err = np.hypot(back[..., 0] - u0, back[..., 1] - v0)
                rel = np.abs(zb - depths[r]) / depths[r]
                ok = inside & np.isfinite(dj) & (err < tol_px) & (rel < tol_rel)
                nearer = inside & np.isfinite(dj) & (dj < z * (1 - tol_rel))
            seen = inside & np.isfinite(dj) & ~nearer
            agree += ok
            sees += seen | ok
            acc += np.where(ok[..., None], xj, 0.0)
            matches[j] = (ok, ri * Wj + ci)
        fused = acc / np.maximum(agree + 1, 1)[..., None]
        fused[~has] = np.nan
        out.append(Consistency(agree, sees, pts[r], fused, matches))
    return out


@dataclass
class FusedPoints:
    """The fused point set.

    Attributes:
        points: [N, 3] float64 world points.
        colors: [N, 3] uint8.
        conf: [N] float32 confidence of the pixel each came from.
        view, pixel: [N] int64, the view and flat pixel index each came from.
        observations: per view, ([M] flat pixel index, [M] point index): every pixel that
            observes a point (its own pixel and the agreeing views' pixels).
    """

    points: np.ndarray
    colors: np.ndarray
    conf: np.ndarray
    view: np.ndarray
    pixel: np.ndarray
    observations: dict[int, tuple[np.ndarray, np.ndarray]]


def fuse(cons: list[Consistency], keep: list[np.ndarray], conf: list[np.ndarray],
         colors: list[np.ndarray]) -> FusedPoints:
    """One point per surface patch from the kept pixels of every view (module docstring).

    Args:
        cons: :func:`check_consistency`'s result per view.
        keep: per view [H, W] bool, the pixels kept.
        conf: per view [H, W] confidence.
        colors: per view [H, W, 3] uint8 colours.
    """
    taken = [np.zeros(k.size, bool) for k in keep]
    P, C, Q, V, X = [], [], [], [], []
    obs: dict[int, tuple[list, list]] = {r: ([], []) for r in range(len(cons))}
    offset = 0
    for r, c in enumerate(cons):
        idx = np.flatnonzero(keep[r].ravel() & ~taken[r])
        ids = offset + np.arange(len(idx))
        obs[r][0].append(idx)
        obs[r][1].append(ids)
        for j, (ok, qpix) in c.matches.items():
            okf, qf = ok.ravel()[idx], qpix.ravel()[idx]
            obs[j][0].append(qf[okf])
            obs[j][1].append(ids[okf])
            if j > r:
                taken[j][qf[okf]] = True
        P.append(c.fused.reshape(-1, 3)[idx])
        C.append(colors[r].reshape(-1, 3)[idx])
        Q.append(conf[r].ravel()[idx])
        V.append(np.full(len(idx), r))
        X.append(idx)
        offset += len(idx)
    cat = (lambda a, shape, dt: np.concatenate(a).astype(dt) if a else np.zeros(shape, dt))
    observations = {r: (cat(px, (0,), np.int64), cat(pi, (0,), np.int64)) for r, (px, pi) in obs.items()}
    return FusedPoints(cat(P, (0, 3), np.float64), cat(C, (0, 3), np.uint8), cat(Q, (0,), np.float32),
                       cat(V, (0,), np.int64), cat(X, (0,), np.int64), observations)
