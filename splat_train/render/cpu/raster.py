"""CPU fast path: the C++ tile blender built on first use, behind backend "cpu".

``raster.cpp`` blends 16 pixels of a tile row per vector instruction
(GCC/Clang vector extensions), bins with a radix depth sort and a counting sort, and reduces the
per-pair gradients once per Gaussian in C. (The scalar kernel it replaced, backend "cpu_v1", is
deleted; their side-by-side timings are recorded in ``benchmarks/README.md``.)

Building, loading (SIMD level chosen at load time), threads: :mod:`splat_train.render.cpu.build`.
If no compiler is present or every build fails, the failure is logged once and
:func:`available` returns False; the public rasterizer then uses the vectorised torch tile code.

Autograd: :class:`_BlendCPU` wraps forward and the hand-written backward (back-to-front
recomputation per pixel, as in 3DGS). Per-pair gradients are written by the tile that owns the
pair and summed per Gaussian in a fixed order, in C: the result does not depend on the thread
count.
"""

from __future__ import annotations

import ctypes
import math
import threading
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from splat_train.render.cpu.build import KERNEL_REGISTRY, kernel_threads, set_kernel_threads
from splat_train.render.cpu.build import Kernel as _Kernel
from splat_train.render.cpu.build import ptr as _ptr
from splat_train.render.cpu.build import run_threaded as _run_threaded
from splat_train.render.cpu.build import suffix as _suffix
from splat_train.render._reference import depth_order
from splat_train.render.projection import TILE_SIZE, Projected

__all__ = [
    "KERNELS", "available", "load_library", "blend_cpu", "build_error", "forward_raw", "backward_raw",
    "tile_pairs_cpu", "backend_functions", "simd_bits", "set_kernel_threads", "kernel_threads",
]

KERNELS = ("cpu",)
_BIN_CHUNKS = 8  # fixed chunks of the depth order for the parallel counting sort
_SPAN_RECORD = 32  # int16 binning record per Gaussian: tiles + 14 row spans (SPREC in the C++)


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    for dt in ("f32", "f64"):
        getattr(lib, f"splat2_forward_{dt}").argtypes = [i64] * 5 + [vp] * 14
        getattr(lib, f"splat2_forward_{dt}").restype = None
        getattr(lib, f"splat2_backward_{dt}").argtypes = [i64] * 6 + [vp] * 16
        getattr(lib, f"splat2_backward_{dt}").restype = None
        getattr(lib, f"splat2_footprint_{dt}").argtypes = [i64, vp, vp, vp, vp, vp, vp, vp]
        getattr(lib, f"splat2_footprint_{dt}").restype = None
        getattr(lib, f"splat2_footprint_scalar_{dt}").argtypes = [i64, vp, vp, vp, vp, vp, vp]
        getattr(lib, f"splat2_footprint_scalar_{dt}").restype = None
    lib.splat2_bin_count.argtypes = [i64, vp, vp, vp, vp, i64, i64, i64, vp, vp, vp]
    lib.splat2_bin_count.restype = None
    lib.splat2_bin_scatter.argtypes = [i64, vp, vp, vp, vp, i64, i64, i64, vp, vp, vp, vp, vp]
    lib.splat2_bin_scatter.restype = None
    lib.splat2_depth_order_f32.argtypes = [i64, vp, vp, vp, vp, vp]
    lib.splat2_depth_order_f32.restype = i64
    for dt in ("f32", "f64"):
        getattr(lib, f"splat2_reduce_{dt}").argtypes = [i64, vp, vp, i64, vp, vp, vp, i64, vp, vp, vp]
        getattr(lib, f"splat2_reduce_{dt}").restype = None
        getattr(lib, f"splat2_active_{dt}").argtypes = [i64, i64, vp]
        getattr(lib, f"splat2_active_{dt}").restype = i64
    lib.splat2_simd_bits.restype = ctypes.c_int
    return lib


_KERNELS = KERNEL_REGISTRY
_KERNELS.update({
    "cpu": _Kernel("cpu", "raster.cpp", 18, True, "splat2_abi_version", _declare),
})


def _kernel(name: str) -> _Kernel:
    if name not in _KERNELS:
        raise ValueError(f"CPU kernel must be one of {KERNELS}, got {name!r}")
    return _KERNELS[name]


def load_library(name: str = "cpu") -> ctypes.CDLL | None:
    """Build (once, cached) and load kernel ``name``; None if disabled or the build failed."""
    return _kernel(name).load()


def available(name: str = "cpu") -> bool:
    """True when kernel ``name`` ("cpu") is built and loaded."""
    return load_library(name) is not None


def build_error(name: str = "cpu") -> str | None:
    """Why kernel ``name`` is unavailable (None when it loaded or was not tried)."""
    return _kernel(name).error


def simd_bits() -> int | None:
    """Vector width (bits) the "cpu" kernel was built for: 512, 256 or 128; None if unavailable."""
    lib = load_library("cpu")
    return None if lib is None else int(lib.splat2_simd_bits())


@dataclass
class Bins:
    """Tile lists of one view (CPU, int64).

    Attributes:
        offsets: [T + 1] tile t owns pairs offsets[t]:offsets[t + 1] (T = tiles_x * tiles_y,
            t = ty * tiles_x + tx).
        gauss: [P] int32 Gaussian index per pair, front to back within a tile.
        tiles_x, tiles_y: tile grid.
        order: [M] visible Gaussians front to back.
        ps: [M + 1] prefix sums of the pair counts in ``order``.
        slot_pair: [P] int32 per slot its pair: Gaussian ``order[r]`` owns slots
            ps[r]:ps[r + 1] (its tiles row-major), and the backward writes pair k's gradients
            to row k, so the reduction sums rows slot_pair[ps[r]:ps[r + 1]]; it skips the
            pairs the backward did not reach (behind every pixel's last contributor; it marks
            them in a [P] byte map), whose rows it never writes.
        fp: [N, 8] float64 footprints (with means2d, conics and opacities given to
            :func:`bin_cpu`): then the lists hold only the tiles each Gaussian's alpha >= 1/255
            ellipse can reach, and the kernels reuse the footprints (so they must be called
            with the same means2d, conics and opacities).
        tile_order: [T] int32: the order in which the blend's threads take the
            tiles, longest list first (a tile's cost grows with its list; taking the long
            ones last left a thread idle while the other finished one: 2-thread blend at 93-95 %
            of the one-thread time / 2 on the fern checkpoint). Every tile is blended the same
            whichever thread takes it when: the order changes no result.
        visible: [N] bool: the Gaussians in ``order`` (the backward's reduction
            zeroes the gradient rows of the others itself).
        rows_hit: [P] int16 (written by :func:`forward_raw`, read by
            :func:`backward_raw`): bit i of pair k set when the forward blended at least one
            pixel of tile row i with it. The backward visits only those rows (in the others no
            pixel passes its mask: skipping them changes no bit) and skips pairs with none.
    """

    offsets: Tensor
    gauss: Tensor
    tiles_x: int
    tiles_y: int
    order: Tensor | None = None
    ps: Tensor | None = None
    fp: Tensor | None = None
    slot_pair: Tensor | None = None
    tile_order: Tensor | None = None
    visible: Tensor | None = None
    rows_hit: Tensor | None = None


_scratch_bufs: dict[str, Tensor] = {}
_scratch_lock = threading.Lock()


def _scratch(name: str, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
    """A reused scratch tensor (grow-only, one per name; callers hold the lock that guards
    that name while they use it: ``_scratch_lock`` for binning's, ``_workspace_lock`` for the
    backward's pair gradients): binning's temporaries (spans, the radix sort's buffers, pair
    counts) are tens of MB at 200k Gaussians, and fresh allocations of that size are fresh
    pages, whose page faults each iteration would pay again."""
    numel = math.prod(shape)
    buf = _scratch_bufs.get(name)
    if buf is None or buf.dtype != dtype or buf.numel() < numel:
        buf = torch.empty(max(numel, 1), dtype=dtype)
        _scratch_bufs[name] = buf
    return buf[:numel].view(shape)


def _depth_order(lib, depths: Tensor, visible: Tensor) -> Tensor:
    """:func:`splat_train.render._reference.depth_order` by the kernel's radix sort (float32 depths).
    Call with ``_scratch_lock`` held."""
    if depths.dtype != torch.float32:
        return depth_order(depths, visible).contiguous()
    n = depths.numel()
    d = depths.detach().contiguous()
    vis = visible.contiguous().view(torch.uint8)  # bool is one byte 0/1: no copy
    order = torch.empty(n, dtype=torch.int64)
    buf = _scratch("sort_buf", (n,), torch.int64)
    keys = _scratch("sort_keys", (2 * n,), torch.int32)
    m = lib.splat2_depth_order_f32(n, _ptr(d), _ptr(vis), _ptr(order), _ptr(buf), _ptr(keys))
    return order[:m]


def bin_cpu(depths: Tensor, rect: Tensor, visible: Tensor, width: int, height: int, kernel: str = "cpu",
            means2d: Tensor | None = None, conics: Tensor | None = None, opacities: Tensor | None = None) -> Bins:
    """Depth order and per-tile Gaussian lists in C (counting sort).

    Args:
        depths: [N] camera z. rect: [N, 4] tile rectangle (x_min, x_max, y_min, y_max), max
            exclusive. visible: [N] bool. width, height: image size in pixels.
        kernel: "cpu" (radix depth sort, also the per-Gaussian pair lists).
        means2d [N, 2], conics [N, 3], opacities [N]: optional (all three, one
            dtype): keep, within each rectangle, only the tiles where the Gaussian's alpha can
            reach 1/255 (the blend's own footprint test, see ``tile_span`` in
            ``raster.cpp``); the dropped pairs would blend no pixel, so images and
            gradients are unchanged while binning, blending and reduction visit fewer pairs.

    Returns:
        :class:`Bins`; without the footprint arguments the same lists as
        :func:`splat_train.render._tiles.tile_pairs`, with them a subsequence of each tile's list.
    """
    lib = load_library(kernel)
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = tiles_x * tiles_y
    with torch.no_grad(), _scratch_lock:
        r = rect.to(torch.int64).contiguous()
        fp = spans = None
        sort = lambda: _depth_order(lib, depths, visible)  # noqa: E731
        if means2d is not None and max(tiles_x, tiles_y) < 2**15:  # int16 tile rectangles
            dt = means2d.dtype
            mu, co, op = (t.detach().to(dt).contiguous() for t in (means2d, conics, opacities))
            spans = _scratch("spans", (r.shape[0], _SPAN_RECORD), torch.int16)
            # the (serial) depth sort runs on this thread while the others start the footprints
            fp, order = _footprints(lib, mu, co, op, _suffix(dt), r, spans, first=sort)
        else:
            order = sort()
        fpp = _ptr(fp) if fp is not None else None
        spp = _ptr(spans) if spans is not None else None
        m = order.numel()
        counts = _scratch("counts", (_BIN_CHUNKS, n_tiles), torch.int64)
        area = _scratch("area", (m,), torch.int64)
        _run_threaded(lib.splat2_bin_count, m, _ptr(order), _ptr(r), fpp, spp, tiles_x, n_tiles, _BIN_CHUNKS,
                      _ptr(counts), _ptr(area))
        per_tile = counts.sum(0)
        offsets = torch.zeros(n_tiles + 1, dtype=torch.int64)
        torch.cumsum(per_tile, 0, out=offsets[1:])
        base = (offsets[:-1][None, :] + torch.cumsum(counts, 0) - counts).contiguous()
        ps = torch.empty(m + 1, dtype=torch.int64)
        ps[0] = 0
        torch.cumsum(area, 0, out=ps[1:])
        total = int(offsets[-1])
        if total >= 2**31:
            raise ValueError(f"{total} tile-Gaussian pairs: the 'cpu' kernel indexes pairs with int32 (< 2**31)")
        # int32 lists: half the bytes of int64 for the scatter's ~2 random writes per pair and
        # for every read in the blend (N and the pair count stay far below 2**31 on a CPU)
        gauss = torch.empty(total, dtype=torch.int32)
        slot_pair = torch.empty(total, dtype=torch.int32)
        _run_threaded(lib.splat2_bin_scatter, m, _ptr(order), _ptr(r), fpp, spp, tiles_x, n_tiles, _BIN_CHUNKS,
                      _ptr(base), _ptr(ps), _ptr(gauss), _ptr(slot_pair))
    tile_order = torch.argsort(per_tile, descending=True, stable=True).to(torch.int32)
    return Bins(offsets, gauss, tiles_x, tiles_y, order, ps, fp, slot_pair, tile_order, visible.contiguous())


def tile_pairs_cpu(
    depths: Tensor, rect: Tensor, visible: Tensor, width: int, height: int, kernel: str = "cpu"
) -> tuple[Tensor, Tensor, int, int]:
    """:func:`splat_train.render._tiles.tile_pairs` with the list building in C (counting sort).

    Same results (offsets [T + 1], gauss [P], tiles_x, tiles_y); O(pairs) instead of a sort of
    all pairs.
    """
    b = bin_cpu(depths, rect, visible, width, height, kernel)
    return b.offsets, b.gauss.to(torch.int64), b.tiles_x, b.tiles_y


def forward_raw(means2d, conics, features, opacities, bins: Bins, width: int, height: int, kernel: str = "cpu",
                with_count: bool = True):
    """Run the forward kernel (no autograd).

    Args:
        means2d [N, 2], conics [N, 3], features [N, F], opacities [N] as in :func:`blend_cpu`
        (one dtype, float32 or float64); bins from :func:`bin_cpu` with the same ``kernel``.
        with_count: also count the Gaussians blended into each pixel (without, the
            kernel skips that bookkeeping and count is None).

    Returns:
        accum [H, W, F], T_final [H, W], last [H, W] int32 (1 + index of the last
        contributing pair within the pixel's tile list, 0 if none) and count [H, W] int32
        (Gaussians blended into the pixel; None when not ``with_count``).
    """
    lib = load_library(kernel)
    dt = means2d.dtype
    suffix = _suffix(dt)
    m, co, fe, op = (t.detach().to(dt).contiguous() for t in (means2d, conics, features, opacities))
    nf = fe.shape[1]
    if nf > 16:
        raise ValueError(f"the 'cpu' kernel blends at most 16 feature channels, got {nf}")
    accum = torch.empty(height, width, nf, dtype=dt)
    t_final = torch.empty(height, width, dtype=dt)
    last = torch.empty(height, width, dtype=torch.int32)
    count = torch.empty(height, width, dtype=torch.int32) if with_count else None
    fp = bins.fp if bins.fp is not None else _footprints(lib, m, co, op, suffix)
    bins.rows_hit = torch.empty(bins.gauss.numel(), dtype=torch.int16)  # fresh: a saved one stays valid
    _run_threaded(
        getattr(lib, f"splat2_forward_{suffix}"),
        bins.tiles_x, bins.tiles_y, width, height, nf, _ptr(bins.offsets), _ptr(bins.gauss), _ptr(m), _ptr(co),
        _ptr(op), _ptr(fe), _ptr(fp), _ptr(accum), _ptr(t_final), _ptr(last),
        None if count is None else _ptr(count), _ptr(bins.rows_hit), _tile_order(bins),
    )
    return accum, t_final, last, count


def _footprints(lib, means2d: Tensor, conics: Tensor, opacities: Tensor, suffix: str,
                rect: Tensor | None = None, spans: Tensor | None = None, first=None):
    """[N, 8] float64 per-Gaussian footprint of the "cpu" kernel (rows / columns it can reach;
    contiguous tensors of the kernel's dtype); with rect [N, 4] int64 and spans [N, 32] int16
    also its binning record (tiles and per-row spans; spans is written). With ``first`` (see
    :func:`splat_train.render.cpu.build.run_threaded`): (footprints, ``first()``'s result)."""
    fp = torch.empty(conics.shape[0], 8, dtype=torch.float64)
    res = _run_threaded(getattr(lib, f"splat2_footprint_{suffix}"), conics.shape[0], _ptr(conics), _ptr(opacities),
                        _ptr(means2d), None if rect is None else _ptr(rect), _ptr(fp),
                        None if spans is None else _ptr(spans), first=first)
    return fp if first is None else (fp, res)


def _tile_order(bins: Bins):
    return None if bins.tile_order is None else _ptr(bins.tile_order)


# Held while the backward uses its pair-gradient buffer (_scratch "pair_<dtype>").
_workspace_lock = threading.Lock()


def backward_raw(means2d, conics, features, opacities, bins: Bins, width: int, height: int,
                 t_final: Tensor, last: Tensor, v_accum: Tensor, v_t: Tensor, kernel: str = "cpu",
                 rows_hit: Tensor | None = None) -> Tensor:
    """Run the backward kernel and reduce per Gaussian (no autograd).

    Args:
        means2d .. bins, width, height as in :func:`forward_raw`; t_final [H, W] and last
        [H, W] int32 from it; v_accum [H, W, F] and v_t [H, W] the cotangents; rows_hit
        [P] int16 from it (default ``bins.rows_hit``, which the last forward_raw with
        these bins wrote).

    Returns:
        [N, 6 + F] per-Gaussian gradients (v_mx, v_my, v_a, v_b, v_c, v_opacity, v_features),
        zero rows for Gaussians in no tile.
    """
    lib = load_library(kernel)
    dt = means2d.dtype
    suffix = _suffix(dt)
    m, co, fe, op = (t.detach().to(dt).contiguous() for t in (means2d, conics, features, opacities))
    nf, n = fe.shape[1], m.shape[0]
    v_accum = v_accum.to(dt).contiguous()
    v_t = v_t.to(dt).contiguous()
    t_final, last = t_final.contiguous(), last.contiguous()
    rows_hit = bins.rows_hit if rows_hit is None else rows_hit
    if rows_hit is None or rows_hit.numel() != bins.gauss.numel():
        raise ValueError("backward_raw needs the rows the forward blended (bins.rows_hit): run forward_raw "
                         "with these bins first")
    fp = bins.fp if bins.fp is not None else _footprints(lib, m, co, op, suffix)
    vis = bins.visible.view(torch.uint8) if bins.visible is not None and bins.visible.numel() == n else None
    # the reduction writes every row: the Gaussians in order, and with vis the others' zeros
    v = torch.empty(n, 6 + nf, dtype=dt) if vis is not None else torch.zeros(n, 6 + nf, dtype=dt)
    # trailing feature channels whose cotangent is zero everywhere are skipped (exact): one
    # pass in C over v_accum (instead of strided torch .any() calls per channel)
    n_active = int(getattr(lib, f"splat2_active_{suffix}")(v_accum.numel() // max(nf, 1), nf, _ptr(v_accum)))
    # the buffer needs no clearing: "cpu" writes the row of every pair it reaches and the
    # reduction reads only those (live: one byte per pair, written by the backward)
    live = torch.empty(bins.gauss.numel(), dtype=torch.uint8)
    with _workspace_lock:
        # reused across calls: a fresh 60 MB buffer per iteration (1.5 M pairs at 100k
        # Gaussians, 512x512) cost its page faults every time
        v_pair = _scratch(f"pair_{dt}", (bins.gauss.numel(), 6 + nf), dt)
        _run_threaded(
            getattr(lib, f"splat2_backward_{suffix}"),
            bins.tiles_x, bins.tiles_y, width, height, nf, n_active, _ptr(bins.offsets), _ptr(bins.gauss), _ptr(m), _ptr(co),
            _ptr(op), _ptr(fe), _ptr(fp), _ptr(t_final), _ptr(last), _ptr(rows_hit), _ptr(v_accum),
            _ptr(v_t), _ptr(v_pair), _ptr(live), _tile_order(bins),
        )
        _run_threaded(getattr(lib, f"splat2_reduce_{suffix}"), bins.order.numel(), _ptr(bins.order), _ptr(bins.ps),
                      6 + nf, _ptr(v_pair), _ptr(bins.slot_pair), _ptr(live), n,
                      None if vis is None else _ptr(vis), _ptr(v))
    return v


@dataclass
class KernelFunctions:
    """The raw entries of one kernel (benchmarks and profiling)."""

    tile_pairs: Callable[..., Bins]
    forward_raw: Callable
    backward_raw: Callable


def backend_functions(kernel: str) -> KernelFunctions:
    """Raw (no-autograd) entries of kernel ``kernel`` ("cpu")."""
    _kernel(kernel)
    return KernelFunctions(
        tile_pairs=lambda *a, **kw: bin_cpu(*a, kernel=kernel, **kw),
        forward_raw=lambda *a: forward_raw(*a, kernel=kernel),
        backward_raw=lambda *a: backward_raw(*a, kernel=kernel),
    )


class _BlendCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, features, opacities, bins, width, height, kernel):
        accum, t_final, last, _ = forward_raw(means2d, conics, features, opacities, bins, width, height, kernel,
                                              with_count=False)
        m, co, fe, op = (t.detach().contiguous() for t in (means2d, conics, features, opacities))
        ctx.save_for_backward(m, co, fe, op, t_final, last)
        ctx.extra = (bins, width, height, kernel, bins.rows_hit)
        ctx.set_materialize_grads(False)  # an unused output's cotangent stays None (zeros made below)
        return accum, t_final

    @staticmethod
    def backward(ctx, v_accum, v_t):
        m, co, fe, op, t_final, last = ctx.saved_tensors
        bins, width, height, kernel, rows_hit = ctx.extra
        dt, nf = m.dtype, fe.shape[1]
        v_accum = torch.zeros(height, width, nf, dtype=dt) if v_accum is None else v_accum
        v_t = torch.zeros(height, width, dtype=dt) if v_t is None else v_t
        v = backward_raw(m, co, fe, op, bins, width, height, t_final, last, v_accum, v_t, kernel, rows_hit)
        return v[:, 0:2], v[:, 2:5], v[:, 6:], v[:, 5], None, None, None, None


def blend_cpu(proj: Projected, features: Tensor, opacities: Tensor, kernel: str = "cpu") -> tuple[Tensor, Tensor]:
    """C++ tile blending with a hand-written backward (CPU tensors, float32 or float64).

    Arguments and results as :func:`splat_train.render._reference.blend_dense`: ``proj`` the
    screen-space Gaussians of one image (pixels, COLMAP convention; 16-pixel tiles, the
    kernel's), ``features`` [N, F], ``opacities`` [N]; returns accum [H, W, F] (no
    background) and final transmittance [H, W], rows = image y. ``kernel``: "cpu" (the SIMD
    kernel).
    """
    means2d = proj.means2d
    if means2d.device.type != "cpu":
        raise ValueError(f"the CPU kernel needs CPU tensors, got {means2d.device}; use backend='torch'")
    if proj.tile_size != TILE_SIZE:
        raise ValueError(f"the CPU kernel bins {TILE_SIZE}-pixel tiles, got a projection with tile_size "
                         f"{proj.tile_size}; use backend='torch'")
    if load_library(kernel) is None:
        raise RuntimeError(f"CPU rasterizer kernel {kernel!r} unavailable: {build_error(kernel)}; use backend='torch'")
    dt = means2d.dtype
    width, height = proj.width, proj.height
    conics, features, opacities = proj.conics.to(dt), features.to(dt), opacities.to(dt)
    # tight tile lists (only tiles the alpha >= 1/255 ellipse reaches)
    bins = bin_cpu(proj.depths, proj.rect, proj.visible, width, height, kernel, means2d, conics, opacities)
    return _BlendCPU.apply(means2d, conics, features, opacities, bins, width, height, kernel)
