"""The trainable Gaussians: torch parameters in the 3DGS parameterisation and their Adam.

Parameters (N Gaussians, world frame of the seed PLY):

* ``means`` [N, 3] centres,
* ``sh_dc`` [N, 3] degree-0 SH coefficients, ``sh_rest`` [N, 15, 3] bands 1..3,
* ``opacity`` [N] logit(alpha),
* ``scales`` [N, 3] log of the per-axis standard deviations,
* ``quats`` [N, 4] rotations (w, x, y, z), not kept normalised (the rasterizer normalises).

One Adam holds one parameter group per tensor (``group["name"]`` is the key above), so that
densification can rebuild each group with its optimizer state (:mod:`splat_train.strategy.densify`).
"""

from __future__ import annotations

import numpy as np
import torch

from camio.ply import SH_DEGREE, GaussianCloud
from splat_train.config import TrainConfig
from splat_train.render.cpu import optim as cpu_optim
from splat_train.render.sh import sh_concat

__all__ = ["PARAM_NAMES", "params_from_cloud", "params_to_cloud", "make_optimizer", "adam_step", "fused_adam_step",
           "activated", "sh_coeffs", "position_lr"]

PARAM_NAMES = ("means", "sh_dc", "sh_rest", "opacity", "scales", "quats")


def params_from_cloud(cloud: GaussianCloud, sh_degree: int = SH_DEGREE, device: str | torch.device = "cpu"
                      ) -> dict[str, torch.nn.Parameter]:
    """Trainable float32 parameters from a seed cloud; ``sh_rest`` is zero-padded (or cut) to
    ``(sh_degree + 1)^2 - 1`` coefficients. Quaternions that are zero become identity."""
    n = len(cloud)
    k_rest = (sh_degree + 1) ** 2 - 1
    rest = np.zeros((n, k_rest, 3), np.float32)
    k = min(k_rest, cloud.sh_rest.shape[1])
    rest[:, :k] = cloud.sh_rest[:, :k]
    quats = cloud.quats.copy()
    bad = ~np.isfinite(quats).all(1) | (np.linalg.norm(quats, axis=1) < 1e-12)
    quats[bad] = (1.0, 0.0, 0.0, 0.0)
    arrays = {
        "means": cloud.means, "sh_dc": cloud.sh_dc, "sh_rest": rest,
        "opacity": cloud.opacity_logit, "scales": cloud.log_scales, "quats": quats,
    }
    for key, a in arrays.items():
        if not np.isfinite(a).all():
            raise ValueError(f"seed cloud has non-finite {key}: fix the seed PLY")
    return {key: torch.nn.Parameter(torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32,
                                                    device=device))
            for key, a in arrays.items()}


def params_to_cloud(params: dict[str, torch.Tensor]) -> GaussianCloud:
    """The current Gaussians as a :class:`camio.ply.GaussianCloud` (float32 numpy)."""
    get = lambda k: params[k].detach().cpu().float().numpy()  # noqa: E731
    return GaussianCloud(means=get("means"), sh_dc=get("sh_dc"), sh_rest=get("sh_rest"),
                         opacity_logit=get("opacity"), log_scales=get("scales"), quats=get("quats"))


def position_lr(cfg: TrainConfig, iteration: int, extent: float) -> float:
    """Exponential position rate: log-linear from lr_init to lr_final (both x extent) over
    the run; ``iteration`` is 1-based (3DGS ``get_expon_lr_func`` with max_steps = iterations)."""
    o = cfg.optim
    t = min(max((iteration - 1) / max(cfg.run.iterations - 1, 1), 0.0), 1.0)
    lr0 = o.lr_position_init * extent
    lr1 = o.lr_position_final * extent
    return float(np.exp(np.log(lr0) * (1.0 - t) + np.log(lr1) * t))


def make_optimizer(params: dict[str, torch.nn.Parameter], cfg: TrainConfig, extent: float
                   ) -> torch.optim.Adam:
    """Adam with one named group per parameter at the rates of docs/reference.md section 3.

    The fused implementation (one pass per parameter tensor) on CPU and CUDA floating-point
    parameters, several times faster than the default per-tensor loop at 100k Gaussians
    (benchmarks/README.md). Same update rule, rounding differs.
    """
    o = cfg.optim
    lrs = {"means": o.lr_position_init * extent, "sh_dc": o.lr_sh_dc, "sh_rest": o.lr_sh_rest,
           "opacity": o.lr_opacity, "scales": o.lr_scaling, "quats": o.lr_rotation}
    groups = [{"params": [params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES]
    fused = all(params[k].device.type in ("cpu", "cuda") and params[k].is_floating_point() for k in PARAM_NAMES)
    return torch.optim.Adam(groups, lr=0.0, eps=o.adam_eps, fused=fused or None)


def adam_step(opt: torch.optim.Adam) -> None:
    """One step of the trainer's Adam by the fastest path that applies: torch's fused kernel
    called directly (:func:`fused_adam_step`, off the CPU), else the C++ kernel on the CPU
    (:func:`splat_train.render.cpu.optim.adam_step`, which runs ``opt.step()`` where it does not apply)."""
    if not fused_adam_step(opt):
        cpu_optim.adam_step(opt)


def fused_adam_step(opt: torch.optim.Adam, devices: tuple[str, ...] = ("cuda",)) -> bool:
    """``opt.step()`` of a fused Adam (:func:`make_optimizer`'s) as its own kernel calls: one
    ``torch._foreach_add_`` of the step counts and one ``torch._fused_adam_`` per group, which
    is what ``opt.step()`` runs, without its per-group Python (about 40 us per group per
    iteration; a training step on a GPU is a few ms). Same update, same state (``step``,
    ``exp_avg``, ``exp_avg_sq``), so checkpoints, densification and ``opt.step()`` itself go on
    with it.

    Returns:
        False (nothing done) unless every parameter is on one of ``devices`` with its gradient
        and its state already created by a first ``opt.step()``, and the optimizer is fused
        Adam without weight decay, amsgrad, maximize or a grad scaler.
    """
    d = opt.defaults
    if not isinstance(opt, torch.optim.Adam) or not d.get("fused") or d.get("capturable") or d.get("differentiable"):
        return False
    rows = []
    for g in opt.param_groups:
        if g.get("weight_decay", 0) != 0 or g.get("amsgrad") or g.get("maximize"):
            return False
        for p in g["params"]:
            st = opt.state.get(p)
            if p.grad is None or p.device.type not in devices or not st or "exp_avg" not in st:
                return False
            rows.append((g, p, st))
    if not rows:
        return False
    with torch.no_grad():
        torch._foreach_add_([st["step"] for _, _, st in rows], 1)
        for g, p, st in rows:
            b1, b2 = g["betas"]
            torch._fused_adam_([p], [p.grad], [st["exp_avg"]], [st["exp_avg_sq"]], [], [st["step"]],
                               lr=float(g["lr"]), beta1=float(b1), beta2=float(b2), weight_decay=0.0,
                               eps=float(g["eps"]), amsgrad=False, maximize=False)
    return True


def activated(params: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(scales [N, 3] linear, opacities [N] in (0, 1), quats [N, 4] as stored)."""
    return torch.exp(params["scales"]), torch.sigmoid(params["opacity"]), params["quats"]


def sh_coeffs(params: dict[str, torch.Tensor], degree: int) -> torch.Tensor:
    """The SH coefficients of the active ``degree``: [N, (degree + 1)^2, 3]."""
    return sh_concat(params["sh_dc"], params["sh_rest"], degree)
