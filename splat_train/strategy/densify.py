"""Adaptive density control of 3DGS (clone, split, prune, opacity reset), gsplat style.

:class:`DensifyStrategy` holds the settings; its running statistics live outside it in a plain
dict of tensors (``init_state``) so that they can be checkpointed. The plain ops
:func:`duplicate`, :func:`split`, :func:`remove` and :func:`reset_opacity` rewrite the
parameter dict *and* the Adam state of every group consistently:

* new rows (clones, split children) start with zero Adam moments (as in 3DGS);
* removed rows drop their moments; kept rows keep theirs; Adam's step count is unchanged;
* an opacity reset zeroes the opacity group's moments.

Parameters follow :mod:`splat_train.gaussians` (log scales, logit opacity, w x y z quats).

View-space gradient units: the accumulated statistic is the norm of d loss / d (2D mean) in
normalised device coordinates, i.e. the pixel-space gradient times (W / 2, H / 2), which is
what the 3DGS threshold 2e-4 refers to (gsplat converts the same way).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import Callable, ClassVar

import torch

from splat_train.render.cpu import optim as cpu_optim
from splat_train.strategy.base import Strategy

__all__ = ["DensifyStrategy", "cap_candidates", "duplicate", "split", "split_children", "remove", "reset_opacity",
           "quat_to_rotmat", "update_params"]

log = logging.getLogger(__name__)

Params = dict[str, torch.nn.Parameter]


@functools.lru_cache(maxsize=64)
def _ndc_scale(width: int, height: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """[2] (W / 2, H / 2) on ``device``: pixel -> NDC gradient units. Cached, because making a
    device tensor from host numbers is a copy that waits for the device's queue."""
    return torch.tensor([width / 2.0, height / 2.0], dtype=dtype, device=device)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm > 0 -> [N, 3, 3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def update_params(
    params: Params,
    optimizer: torch.optim.Optimizer,
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    state_fn: Callable[[str, torch.Tensor], torch.Tensor],
    names: tuple[str, ...] | None = None,
) -> None:
    """Replace ``params[name]`` by ``param_fn(name, old)`` and each per-row Adam state tensor
    (``exp_avg``, ``exp_avg_sq``) by ``state_fn(name, old_state)``, in place of the group's
    parameter. Scalar state (``step``) is kept."""
    names = tuple(params) if names is None else names
    for group in optimizer.param_groups:
        name = group.get("name")
        if name not in names:
            continue
        old = group["params"][0]
        new = torch.nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        st = optimizer.state.pop(old, None)
        if st is not None:
            for key, v in list(st.items()):
                if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == old.shape[0]:
                    st[key] = state_fn(name, v)
            optimizer.state[new] = st
        group["params"][0] = new
        params[name] = new


def _append_zero_state(n_new: int) -> Callable[[str, torch.Tensor], torch.Tensor]:
    return lambda name, v: torch.cat([v, v.new_zeros((n_new, *v.shape[1:]))])


def duplicate(params: Params, optimizer: torch.optim.Optimizer, mask: torch.Tensor) -> int:
    """Clone the Gaussians selected by ``mask`` [N] bool (copies appended at the end).
    Returns the number added."""
    sel = mask.nonzero().squeeze(1)
    update_params(params, optimizer, lambda name, p: torch.cat([p, p[sel]]),
                  _append_zero_state(len(sel)))
    return len(sel)


def split_children(params: Params, sel: torch.Tensor, generator: torch.Generator | None = None,
                   n_children: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres and log scales of the children of the Gaussians ``sel`` [M] (row indices), 3DGS:
    centres drawn from N(mean, R diag(s^2) R^T) (one ``randn((n_children, M, 3))`` draw from
    ``generator``), scales s / (0.8 n_children).

    Returns:
        (means [n_children M, 3], log scales [n_children M, 3]): child 0 of every parent,
        then child 1, ...
    """
    m = len(sel)
    with torch.no_grad():
        scales = torch.exp(params["scales"][sel])  # [M, 3]
        rot = quat_to_rotmat(params["quats"][sel])  # [M, 3, 3]
        eps = torch.randn((n_children, m, 3), generator=generator, dtype=scales.dtype,
                          device="cpu").to(scales.device)
        offsets = torch.einsum("mij,cmj->cmi", rot, eps * scales[None])  # [C, M, 3]
        children_means = (params["means"][sel][None] + offsets).reshape(-1, 3)
        children_scales = torch.log(scales / (0.8 * n_children)).repeat(n_children, 1)
    return children_means, children_scales


def split(params: Params, optimizer: torch.optim.Optimizer, mask: torch.Tensor,
          generator: torch.Generator | None = None, n_children: int = 2) -> int:
    """Replace each Gaussian selected by ``mask`` [N] bool by ``n_children`` children (3DGS):
    centres drawn from N(mean, R diag(s^2) R^T), scales s / (0.8 n_children), the other
    parameters copied. The parents are removed; survivors keep their order and the children
    are appended. Returns the net number added."""
    sel = mask.nonzero().squeeze(1)
    keep = (~mask).nonzero().squeeze(1)
    m = len(sel)
    children_means, children_scales = split_children(params, sel, generator, n_children)

    def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
        if name == "means":
            child = children_means
        elif name == "scales":
            child = children_scales
        else:
            child = p[sel].repeat(n_children, *([1] * (p.dim() - 1)))
        return torch.cat([p[keep], child])

    def state_fn(name: str, v: torch.Tensor) -> torch.Tensor:
        return torch.cat([v[keep], v.new_zeros((n_children * m, *v.shape[1:]))])

    update_params(params, optimizer, param_fn, state_fn)
    return (n_children - 1) * m


def remove(params: Params, optimizer: torch.optim.Optimizer, mask: torch.Tensor) -> int:
    """Delete the Gaussians selected by ``mask`` [N] bool. Returns the number removed."""
    keep = (~mask).nonzero().squeeze(1)
    update_params(params, optimizer, lambda name, p: p[keep], lambda name, v: v[keep])
    return int(mask.sum())


def reset_opacity(params: Params, optimizer: torch.optim.Optimizer, value: float = 0.01) -> None:
    """Clamp every opacity to at most ``value`` (stored as logit) and zero its Adam moments."""
    cap = float(torch.logit(torch.tensor(value, dtype=torch.float64)))
    update_params(params, optimizer, lambda name, p: p.clamp_max(cap),
                  lambda name, v: torch.zeros_like(v), names=("opacity",))


def cap_candidates(clone_mask: torch.Tensor, split_mask: torch.Tensor, grads: torch.Tensor,
                   room: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep the best densification candidates that fit in ``room`` new Gaussians.

    Each clone and each split adds one Gaussian. When there are more candidates than room,
    the ones with the largest mean view-space gradient are kept (ties: the lower row), the
    others wait for a later densification; with no room, none is kept.

    Args:
        clone_mask, split_mask: [N] bool, disjoint.
        grads: [N] mean view-space gradient norm (the densification statistic).
        room: new Gaussians allowed (cap - current count; <= 0 means none).

    Returns:
        (clone_mask, split_mask) restricted to the kept candidates.
    """
    cand = clone_mask | split_mask
    n_cand = int(cand.sum())
    if n_cand <= room:
        return clone_mask, split_mask
    keep = torch.zeros_like(cand)
    if room > 0:
        score = torch.where(cand, grads, torch.full_like(grads, -float("inf")))
        # a stable sort, so that equal gradients keep the lower row whatever the device
        order = torch.sort(score, descending=True, stable=True).indices[:room]
        keep[order] = True
    log.debug("growth cap: %d of %d clone/split candidates kept", int(keep.sum()), n_cand)
    return clone_mask & keep, split_mask & keep


@dataclass
class DensifyStrategy(Strategy):
    """The 3DGS densification schedule and thresholds (iteration counts of this run), made by its
    config (:class:`splat_train.strategy.configs.DefaultStrategyConfig`).

    Attributes:
        densify_from, densify_until, densify_every: densify at iterations it with
            densify_from < it < densify_until and it % densify_every == 0 (1-based; the 3DGS
            test, so a run whose densify_until equals its length never densifies at its
            last step).
        opacity_reset_every: reset at it % opacity_reset_every == 0, it < densify_until; 0:
            never (and then no size prune either: 3DGS prunes by size only after a reset).
        grad_threshold: mean NDC view-space gradient norm that triggers clone / split.
        percent_dense: clone if max scale <= percent_dense * extent, else split.
        prune_opacity: prune alpha below this.
        prune_screen_size, prune_world_size: after the first reset, prune Gaussians whose 2D
            radius exceeded prune_screen_size pixels (0: no screen-size prune) or whose max
            scale exceeds prune_world_size * extent (0: no world-size prune).
        reset_value: opacity after a reset.
        max_gaussians: no more Gaussians than this after clone/split (None: unlimited); when
            the candidates exceed the room, the best are kept (:func:`cap_candidates`).
    """

    densify_from: int
    densify_until: int
    densify_every: int
    opacity_reset_every: int
    grad_threshold: float
    percent_dense: float
    prune_opacity: float
    prune_screen_size: float
    prune_world_size: float
    reset_value: float
    max_gaussians: int | None

    name: ClassVar[str] = "densify"

    @classmethod
    def from_config(cls, cfg, max_gaussians: int | None = None, **overrides) -> "DensifyStrategy":
        """The strategy of :class:`splat_train.config.TrainConfig` ``cfg`` (its schedule and its
        default strategy's settings), with the growth cap ``max_gaussians`` and any field
        replaced by ``overrides``."""
        return cfg.growth.default.build(cfg.growth, cfg.schedule(), max_gaussians, **overrides)

    @staticmethod
    def init_state(n: int, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
        """Running statistics for n Gaussians: grad2d sum [N], count [N], max radius [N]."""
        return {"grad2d": torch.zeros(n, device=device), "count": torch.zeros(n, device=device),
                "max_radii": torch.zeros(n, device=device)}

    def wants_stats(self, iteration: int) -> bool:
        """Whether 1-based ``iteration``'s render statistics are still read (:meth:`update_state`):
        only while densification is still to come; the trainer's render skips them after."""
        return iteration < self.densify_until

    def update_state(self, state: dict[str, torch.Tensor], means2d_grad: torch.Tensor,
                     radii: torch.Tensor, visible: torch.Tensor, width: int, height: int,
                     iteration: int) -> None:
        """Accumulate one view's statistics (only while densification is still to come).

        Args:
            means2d_grad: [N, 2] d loss / d means2d in pixels.
            radii: [N] screen radius in pixels; visible: [N] bool.
        """
        if not self.wants_stats(iteration):
            return
        if cpu_optim.densify_stats(state, means2d_grad.detach(), radii, visible, width, height):
            return  # the same accumulation in C on the kernel's threads (CPU float32)
        # dense masked updates, not boolean indexing (each mask index is a nonzero + gather +
        # scatter over N); the same values
        g = means2d_grad.detach() * _ndc_scale(width, height, means2d_grad.dtype, means2d_grad.device)
        norm = torch.linalg.vector_norm(g, dim=-1)
        # a row with an inf or NaN component has a non-finite norm: one [N] test instead of
        # isfinite(g).all(1) over [N, 2] (it also drops a finite row whose norm overflows,
        # which would only have added inf to the statistic)
        vis = visible & torch.isfinite(norm)
        state["grad2d"].add_(torch.where(vis, norm, 0.0))
        state["count"].add_(vis)
        torch.where(vis, torch.maximum(state["max_radii"], radii.float()), state["max_radii"],
                    out=state["max_radii"])

    def step(self, params: Params, optimizer: torch.optim.Optimizer, state: dict[str, torch.Tensor],
             iteration: int, extent: float, generator: torch.Generator | None = None) -> dict[str, int]:
        """Run whatever the schedule asks at 1-based ``iteration`` (after the optimizer step).

        Returns counts {"cloned", "split", "pruned", "reset"} (zeros when nothing ran).
        """
        out = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if iteration >= self.densify_until:
            return out
        if iteration > self.densify_from and iteration % self.densify_every == 0:
            out.update(self._densify_and_prune(params, optimizer, state, iteration, extent, generator))
        if self.opacity_reset_every > 0 and iteration % self.opacity_reset_every == 0:
            reset_opacity(params, optimizer, self.reset_value)
            out["reset"] = 1
        return out

    def _densify_and_prune(self, params, optimizer, state, iteration, extent, generator) -> dict[str, int]:
        """Clone, split, then prune, as :func:`duplicate`, :func:`split` and :func:`remove` in
        that order would (same rows, same order, same values and Adam moments, same random
        draws), but with one gather per tensor instead of three rewrites of every parameter and
        moment (three densifications of the 10k fern cell at 207k Gaussians: 346, 339, 115 ms
        -> 104, 157, 46 ms, load 2-2.6; the three-step version freed and faulted in more memory).
        tests/test_train_densify.py checks the equality with the three-step composition."""
        n = params["means"].shape[0]
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads >= self.grad_threshold
        big = torch.exp(params["scales"].detach()).amax(1) > self.percent_dense * extent
        clone_mask, split_mask = high & ~big, high & big
        if self.max_gaussians is not None:
            clone_mask, split_mask = cap_candidates(clone_mask, split_mask, grads, self.max_gaussians - n)
        sel_c = clone_mask.nonzero().squeeze(1)
        sel_s = split_mask.nonzero().squeeze(1)
        keep_o = (~split_mask).nonzero().squeeze(1)
        n_c, n_s, n_k = len(sel_c), len(sel_s), len(keep_o)
        # Rows after duplicate() then split(): the originals that are not split (they keep their
        # Adam moments), the clones, then the split children (child 0 of every parent, then
        # child 1); src = the original row each one copies.
        src = torch.cat([keep_o, sel_c, sel_s, sel_s])
        children_means, children_scales = split_children(params, sel_s, generator)
        n_plain = n_k + n_c  # rows that are plain copies of their source row
        radii = torch.cat([state["max_radii"][keep_o], state["max_radii"][sel_c],
                           state["max_radii"].new_zeros(2 * n_s)])
        with torch.no_grad():
            alpha = torch.sigmoid(params["opacity"].detach()[src])
            prune = alpha < self.prune_opacity
            if 0 < self.opacity_reset_every < iteration:
                if self.prune_screen_size > 0:
                    prune |= radii > self.prune_screen_size
                if self.prune_world_size > 0:
                    max_scale = torch.cat([torch.exp(params["scales"].detach()[src[:n_plain]]),
                                           torch.exp(children_scales)]).amax(1)
                    prune |= max_scale > self.prune_world_size * extent
        rows = (~prune).nonzero().squeeze(1)  # surviving rows, in order
        final_src = src[rows]
        child_rows = rows[rows >= n_plain] - n_plain  # surviving children, as rows of children_*
        n_moments = int((rows < n_k).sum())  # survivors that keep their Adam moments come first
        computed = {"means": children_means, "scales": children_scales}

        def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
            out = p.index_select(0, final_src)
            if name in computed and len(child_rows):
                out[len(rows) - len(child_rows):] = computed[name][child_rows]
            return out

        def state_fn(name: str, v: torch.Tensor) -> torch.Tensor:
            out = v.new_zeros((len(rows), *v.shape[1:]))
            out[:n_moments] = v.index_select(0, final_src[:n_moments])
            return out

        update_params(params, optimizer, param_fn, state_fn)
        m = params["means"].shape[0]
        state.update(self.init_state(m, params["means"].device))
        n_pruned = int(prune.sum())
        log.debug("it %d: cloned %d, split %d, pruned %d -> %d Gaussians", iteration, n_c, n_s, n_pruned, m)
        return {"cloned": n_c, "split": n_s, "pruned": n_pruned}
