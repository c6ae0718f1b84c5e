"""The optimizer side of a training iteration on the CPU kernel's threads (``optim.cpp``):
:func:`adam_step` and :func:`densify_stats`.

torch's fused Adam runs on torch's intra-op threads, which the trainer keeps at one (their
OpenMP workers spin after each parallel region on the cores the rasterizer needs next). This
step runs the same update (torch.optim.Adam: no weight decay, amsgrad, maximize) on the
rasterizer's threads over every parameter tensor at once and keeps the optimizer's state in
torch's own layout (``step``, ``exp_avg``, ``exp_avg_sq``), so checkpoints, densification (which
edits those moments) and ``optimizer.step()`` itself keep working on the same state. Where it
does not apply (another device or dtype, a missing gradient, options it does not implement,
the first step, which creates the state) it calls ``optimizer.step()``.
"""

from __future__ import annotations

import ctypes
import math

import torch

from splat_train.render.cpu.build import KERNEL_REGISTRY as _KERNELS
from splat_train.render.cpu.build import Kernel as _Kernel
from splat_train.render.cpu.build import run_threaded as _run_threaded

__all__ = ["available", "adam_step", "densify_stats"]

_CHUNK = 1 << 14  # CHUNK in the C++


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    i64, vp, dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
    lib.splat_adam_f32.argtypes = [i64] + [vp] * 7 + [dbl] * 3 + [vp, vp]  # ..., chunk_start, counter
    lib.splat_adam_f32.restype = None
    lib.splat_densify_stats_f32.argtypes = [i64, vp, i64, vp, vp, dbl, dbl, vp, vp, vp, vp]
    lib.splat_densify_stats_f32.restype = None
    return lib


_KERNELS.setdefault("optim", _Kernel("optim", "optim.cpp", 1, True, "splat_optim_abi_version", _declare))


def available() -> bool:
    """True when the kernel is built and loaded."""
    return _KERNELS["optim"].load() is not None


def _supported(opt: torch.optim.Adam) -> bool:
    """Whether :func:`adam_step` can run ``opt``'s step in C: one set of betas and eps, no
    option it does not implement, CPU float32 contiguous parameters with their gradients and
    torch's state already created."""
    if len({(float(g["betas"][0]), float(g["betas"][1]), float(g["eps"])) for g in opt.param_groups}) != 1:
        return False
    for group in opt.param_groups:
        if (group.get("weight_decay", 0) != 0 or group.get("amsgrad") or group.get("maximize")
                or group.get("differentiable") or group.get("capturable")):
            return False
        for p in group["params"]:
            st = opt.state.get(p)
            if (p.grad is None or p.device.type != "cpu" or p.dtype != torch.float32 or not p.is_contiguous()
                    or p.grad.dtype != torch.float32 or not p.grad.is_contiguous() or not st or "exp_avg" not in st):
                return False
    return True


def adam_step(opt: torch.optim.Adam) -> bool:
    """One step of ``opt`` (a torch.optim.Adam); True when the C++ kernel ran it, False when
    ``opt.step()`` did (see the module doc for when)."""
    if not isinstance(opt, torch.optim.Adam) or not _supported(opt) or not available():
        opt.step()
        return False
    lib = _KERNELS["optim"].load()
    ptrs: dict[str, list[int]] = {"p": [], "g": [], "m": [], "v": []}
    sizes, step_size, bc2_sqrt, starts = [], [], [], [0]
    g0 = opt.param_groups[0]
    betas = (float(g0["betas"][0]), float(g0["betas"][1]), float(g0["eps"]))  # the same in every group
    with torch.no_grad():
        for group in opt.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                st = opt.state[p]
                st["step"] += 1
                t = float(st["step"])
                ptrs["p"].append(p.data_ptr())
                ptrs["g"].append(p.grad.data_ptr())
                ptrs["m"].append(st["exp_avg"].data_ptr())
                ptrs["v"].append(st["exp_avg_sq"].data_ptr())
                sizes.append(p.numel())
                step_size.append(float(group["lr"]) / (1 - b1 ** t))
                bc2_sqrt.append(math.sqrt(1 - b2 ** t))
                starts.append(starts[-1] + (p.numel() + _CHUNK - 1) // _CHUNK)
        nt = len(sizes)
        arr = lambda ct, xs: (ct * nt)(*xs)  # noqa: E731
        args = [arr(ctypes.c_void_p, ptrs[k]) for k in ("p", "g", "m", "v")]
        _run_threaded(lib.splat_adam_f32, nt, *args, arr(ctypes.c_int64, sizes), arr(ctypes.c_double, step_size),
                      arr(ctypes.c_double, bc2_sqrt), betas[0], betas[1], betas[2],
                      (ctypes.c_int64 * (nt + 1))(*starts))
    return True


def densify_stats(state: dict[str, torch.Tensor], means2d_grad: torch.Tensor, radii: torch.Tensor,
                  visible: torch.Tensor, width: int, height: int) -> bool:
    """:meth:`splat_train.strategy.densify.DensifyStrategy.update_state`'s accumulation in C (CPU float32
    statistics, a float32 [N, 2] gradient with unit column stride, int32 radii); False (nothing
    done) where it does not apply.

    Args:
        state: "grad2d", "count", "max_radii" [N] float32 (updated in place).
        means2d_grad: [N, 2] d loss / d means2d in pixels; radii: [N] int32; visible: [N] bool.
    """
    g, st = means2d_grad, state
    keys = ("grad2d", "count", "max_radii")
    if (g.device.type != "cpu" or g.dtype != torch.float32 or g.dim() != 2 or g.shape[1] != 2 or g.stride(1) != 1
            or radii.dtype != torch.int32 or not radii.is_contiguous() or visible.dtype != torch.bool
            or not visible.is_contiguous() or not available()
            or any(st[k].dtype != torch.float32 or not st[k].is_contiguous() or st[k].device.type != "cpu"
                   for k in keys)):
        return False
    n = g.shape[0]
    lib = _KERNELS["optim"].load()
    _run_threaded(lib.splat_densify_stats_f32, n, g.data_ptr(), g.stride(0), radii.data_ptr(),
                  visible.view(torch.uint8).data_ptr(), width / 2.0, height / 2.0,
                  *(st[k].data_ptr() for k in keys))
    return True
