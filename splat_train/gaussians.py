"""The trainable Gaussians: torch parameters in the 3DGS parameterisation and their Adam.

Parameters (N Gaussians, world frame of the seed PLY):

* ``means`` [N, 3] centres,
* ``sh_dc`` [N, 3] degree-0 SH coefficients, ``sh_rest`` [N, 15, 3] bands 1..3,
* ``opacity`` [N] logit(alpha),
* ``scales`` [N, 3] log of the per-axis standard deviations,
* ``quats`` [N, 4] rotations (w, x, y, z), not kept normalised (the rasterizer normalises).

One Adam holds one parameter group per tensor (``group["name"]`` is the key above), so that
densification can rebuild each group with its optimizer state (:mod:`splat_train.densify`).
"""

from __future__ import annotations

import numpy as np
import torch

from camio.ply import SH_DEGREE, GaussianCloud
from splat_train.config import TrainConfig
from splat_train.sh import sh_concat

__all__ = ["PARAM_NAMES", "params_from_cloud", "params_to_cloud", "make_optimizer",
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
    t = min(max((iteration - 1) / max(cfg.iterations - 1, 1), 0.0), 1.0)
    lr0 = cfg.lr_position_init * extent
    lr1 = cfg.lr_position_final * extent
    return float(np.exp(np.log(lr0) * (1.0 - t) + np.log(lr1) * t))


def make_optimizer(params: dict[str, torch.nn.Parameter], cfg: TrainConfig, extent: float
                   ) -> torch.optim.Adam:
    """Adam with one named group per parameter at the rates of docs/reference.md section 3.

    The fused implementation (one pass per parameter tensor) on CPU and CUDA floating-point
    parameters, several times faster than the default per-tensor loop at 100k Gaussians
    (benchmarks/README.md). Same update rule, rounding differs.
    """
    lrs = {"means": cfg.lr_position_init * extent, "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_rest,
           "opacity": cfg.lr_opacity, "scales": cfg.lr_scaling, "quats": cfg.lr_rotation}
    groups = [{"params": [params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES]
    fused = all(params[k].device.type in ("cpu", "cuda") and params[k].is_floating_point() for k in PARAM_NAMES)
    return torch.optim.Adam(groups, lr=0.0, eps=cfg.adam_eps, fused=fused or None)


def activated(params: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(scales [N, 3] linear, opacities [N] in (0, 1), quats [N, 4] as stored)."""
    return torch.exp(params["scales"]), torch.sigmoid(params["opacity"]), params["quats"]


def sh_coeffs(params: dict[str, torch.Tensor], degree: int) -> torch.Tensor:
    """The SH coefficients of the active ``degree``: [N, (degree + 1)^2, 3]."""
    return sh_concat(params["sh_dc"], params["sh_rest"], degree)
