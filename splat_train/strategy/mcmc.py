"""Capped growth by relocation: 3D Gaussian Splatting as Markov Chain Monte Carlo.

Kheradmand et al., "3D Gaussian Splatting as Markov Chain Monte Carlo" (NeurIPS 2024,
arXiv:2404.09591), as gsplat implements it (``gsplat/strategy/mcmc.py`` ``MCMCStrategy``,
``gsplat/strategy/ops.py`` ``relocate``, ``sample_add``, ``inject_noise_to_position``,
``gsplat/relocation.py`` and its CUDA kernel ``gsplat/cuda/csrc/RelocationCUDA.cu``). Instead
of 3DGS's gradient-triggered clone / split / prune (:mod:`splat_train.strategy.densify`), at every
refine iteration:

1. *relocate*: every dead Gaussian (opacity <= ``min_opacity``) is moved onto a live one drawn
   with probability proportional to opacity; the drawn source and its copies share the
   source's opacity and footprint (:func:`relocation_opacity_scale`);
2. *add*: 5 % more Gaussians (never beyond the cap), drawn and split the same way; with
   ``reach_cap``, more where 5 % per step cannot reach the cap within the refine window
   (:func:`growth_target`);

and after every optimiser step the centres take a random step shaped by each Gaussian's
covariance and gated to the nearly transparent ones (:func:`inject_noise`), the "SGLD" noise of
the paper. The count never falls: dead Gaussians are reused, not removed.

Adam moments: the rows written by a relocation or an addition (the sources, whose opacity and
scale changed, and the new copies) start at zero. gsplat zeros the sources and the appended
rows but leaves a relocated row's destination with the moments of the dead Gaussian it
replaces; here that row starts at zero too, as every new Gaussian of :mod:`splat_train.strategy.densify`.

Parameters follow :mod:`splat_train.gaussians` (log scales, logit opacity, w x y z quats).
All draws come from the run's ``torch.Generator`` (CPU), so a run is reproducible and resumes
exactly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import torch

from splat_train.strategy.densify import Params, quat_to_rotmat, update_params
from splat_train.strategy.base import Strategy

__all__ = ["MCMCStrategy", "growth_target", "refine_steps", "relocation_opacity_scale", "relocate", "sample_add", "inject_noise",
           "GROWTH", "MAX_COPIES", "NOISE_K", "NOISE_T"]

log = logging.getLogger(__name__)

# New Gaussians per refine step, as a fraction of the current count (gsplat: int(1.05 N)).
GROWTH = 0.05
# Most copies of one Gaussian that one relocation splits it into (gsplat's binomial table:
# n_max = 51); a source drawn more often is split as if into this many.
MAX_COPIES = 51
# The noise gate sigmoid(-NOISE_K (opacity - NOISE_T)) (gsplat's DEFAULT_MCMC_OPACITY_K / _T):
# ~1 for Gaussians near the dead threshold, ~0 for opaque ones.
NOISE_K = 100.0
NOISE_T = 0.005


@lru_cache(maxsize=None)
def _scale_polynomial(device: torch.device) -> torch.Tensor:
    """[MAX_COPIES + 1, MAX_COPIES] float64 table P with P[n, j - 1] = (-1)^(j-1) C(n, j) / sqrt(j)
    (zero for j > n): the scale denominator of n copies is sum_j P[n, j - 1] o^j.

    The paper's Eq. 9 writes it as sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o^(k+1) / sqrt(k+1)
    (the double loop of gsplat's kernel); summing C(i-1, k) over i gives C(n, k+1)."""
    p = torch.zeros(MAX_COPIES + 1, MAX_COPIES, dtype=torch.float64)
    for n in range(1, MAX_COPIES + 1):
        for j in range(1, n + 1):
            p[n, j - 1] = (-1) ** (j - 1) * math.comb(n, j) / math.sqrt(j)
    return p.to(device)


def relocation_opacity_scale(opacity: torch.Tensor, scales: torch.Tensor, copies: torch.Tensor,
                             min_opacity: float = 0.005) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity and scale of each of ``copies`` Gaussians that replace one (the paper's Eq. 9).

    The new opacity keeps the transmittance of the stack: 1 - (1 - o_new)^n = o, i.e.
    o_new = 1 - (1 - o)^(1/n), then clamped to [min_opacity, 1 - eps] (as gsplat does, for
    numerical safety; the clamp breaks the identity only for nearly dead sources). The new
    scale keeps the stack's integrated footprint: s_new = o / D(o_new) s with
    D(a) = sum_{j=1..n} (-1)^(j-1) C(n, j) a^j / sqrt(j). One copy (n = 1) leaves both as they are.

    Computed in float64 whatever the input dtype (the alternating sum cancels), returned in it.

    Args:
        opacity: [M] opacities in (0, 1) (not logits).
        scales: [M, 3] linear scales (not logs).
        copies: [M] integer number of Gaussians the source becomes (itself included), clamped to
            [1, MAX_COPIES].
        min_opacity: lower clamp of the new opacity.

    Returns:
        (new opacity [M], new scales [M, 3]), dtype and device of ``opacity`` / ``scales``.
    """
    o = opacity.double()
    n = copies.long().clamp(1, MAX_COPIES)
    eps = torch.finfo(opacity.dtype).eps
    o_new = (1.0 - (1.0 - o) ** (1.0 / n.double())).clamp(min_opacity, 1.0 - eps)
    powers = o_new[:, None] ** torch.arange(1, MAX_COPIES + 1, dtype=torch.float64, device=o.device)  # [M, K]
    denom = (_scale_polynomial(o.device)[n] * powers).sum(1)
    s_new = (o / denom)[:, None] * scales.double()
    return o_new.to(opacity.dtype), s_new.to(scales.dtype)


def _draw(weights: torch.Tensor, n: int, generator: torch.Generator | None) -> torch.Tensor:
    """n row indices drawn with replacement in proportion to ``weights`` [M] (on the CPU, from
    ``generator``), on the weights' device."""
    idx = torch.multinomial(weights.detach().float().cpu(), n, replacement=True, generator=generator)
    return idx.to(weights.device)


def _split_sources(params: Params, sources: torch.Tensor, min_opacity: float
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The distinct drawn sources and their new (logit opacity, log scales) when each becomes
    1 + (times drawn) Gaussians.

    Args:
        sources: [K] drawn row indices (repeats allowed).

    Returns:
        (unique rows [U], logit opacity [U], log scales [U, 3]).
    """
    rows, times = torch.unique(sources, return_counts=True)
    with torch.no_grad():
        o_new, s_new = relocation_opacity_scale(torch.sigmoid(params["opacity"].detach()[rows]),
                                                torch.exp(params["scales"].detach()[rows]), times + 1, min_opacity)
    return rows, torch.logit(o_new), torch.log(s_new)


def relocate(params: Params, optimizer: torch.optim.Optimizer, dead: torch.Tensor, min_opacity: float,
             generator: torch.Generator | None = None) -> int:
    """Move every Gaussian selected by ``dead`` [N] bool onto a live one drawn in proportion to
    its opacity: the source's opacity and scale become :func:`relocation_opacity_scale`'s for
    1 + (times drawn) copies, and each dead row becomes a copy of its source (every parameter).
    The sources' and the relocated rows' Adam moments are zeroed. Rows keep their order and the
    count is unchanged. Returns the number relocated (0 when none is dead or none is alive)."""
    dead_rows = dead.nonzero().squeeze(1)
    alive_rows = (~dead).nonzero().squeeze(1)
    if len(dead_rows) == 0 or len(alive_rows) == 0:
        return 0
    weights = torch.sigmoid(params["opacity"].detach()[alive_rows])
    sources = alive_rows[_draw(weights, len(dead_rows), generator)]  # [D], the source of each dead row
    rows, logit_o, log_s = _split_sources(params, sources, min_opacity)
    changed = {"opacity": logit_o, "scales": log_s}
    touched = torch.cat([rows, dead_rows])

    def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
        out = p.clone()
        if name in changed:
            out[rows] = changed[name].to(out.dtype)
        out[dead_rows] = out[sources]
        return out

    def state_fn(name: str, v: torch.Tensor) -> torch.Tensor:
        out = v.clone()
        out[touched] = 0
        return out

    update_params(params, optimizer, param_fn, state_fn)
    return len(dead_rows)


def sample_add(params: Params, optimizer: torch.optim.Optimizer, n_new: int, min_opacity: float,
               generator: torch.Generator | None = None) -> int:
    """Append ``n_new`` Gaussians, each a copy of a row drawn in proportion to opacity; the
    drawn sources' opacity and scale become :func:`relocation_opacity_scale`'s for
    1 + (times drawn) copies. The sources' and the new rows' Adam moments are zero. Returns the
    number added."""
    if n_new <= 0:
        return 0
    sources = _draw(torch.sigmoid(params["opacity"].detach()), n_new, generator)  # [n_new]
    rows, logit_o, log_s = _split_sources(params, sources, min_opacity)
    changed = {"opacity": logit_o, "scales": log_s}

    def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
        out = p.clone()
        if name in changed:
            out[rows] = changed[name].to(out.dtype)
        return torch.cat([out, out[sources]])

    def state_fn(name: str, v: torch.Tensor) -> torch.Tensor:
        out = v.clone()
        out[rows] = 0
        return torch.cat([out, v.new_zeros((n_new, *v.shape[1:]))])

    update_params(params, optimizer, param_fn, state_fn)
    return n_new


def _randn(shape: tuple[int, ...], like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """Standard normal draws of ``shape`` in ``like``'s dtype and device. On the CPU they come
    from ``generator``; on an accelerator from a generator of that device seeded by one draw
    from ``generator`` (still reproducible and resumable from ``generator``'s state, without
    drawing [N, 3] numbers on the host and copying them every iteration)."""
    if like.device.type == "cpu" or generator is None:
        return torch.randn(shape, generator=generator, dtype=like.dtype, device="cpu").to(like.device)
    seed = int(torch.randint(0, 2**62, (1,), generator=generator))
    dev_gen = torch.Generator(device=like.device).manual_seed(seed)
    return torch.randn(shape, generator=dev_gen, dtype=like.dtype, device=like.device)


def inject_noise(params: Params, noise_scale: float, generator: torch.Generator | None = None) -> None:
    """Add to every centre Sigma eps * gate * ``noise_scale`` in place (gsplat's
    ``inject_noise_to_position``), where eps ~ N(0, I_3) [N, 3] (drawn by :func:`_randn`),
    Sigma = R diag(s^2) R^T the Gaussian's world covariance and
    gate = sigmoid(-NOISE_K (opacity - NOISE_T)): the nearly transparent Gaussians explore, the
    opaque ones stay. ``noise_scale`` is the position learning rate times ``noise_lr``."""
    means = params["means"]
    with torch.no_grad():
        eps = _randn(tuple(means.shape), means, generator)
        gate = torch.sigmoid(-NOISE_K * (torch.sigmoid(params["opacity"].detach()) - NOISE_T))
        rot = quat_to_rotmat(params["quats"].detach())  # [N, 3, 3]
        var = torch.exp(2.0 * params["scales"].detach())  # [N, 3]
        # Sigma eps = R (s^2 * (R^T eps))
        local = torch.einsum("nji,nj->ni", rot, eps * (gate * noise_scale)[:, None])
        means.add_(torch.einsum("nij,nj->ni", rot, var * local))


def refine_steps(refine_from: int, refine_until: int, refine_every: int, iteration: int) -> int:
    """How many refine iterations (multiples of ``refine_every`` strictly between
    ``refine_from`` and ``refine_until``) are at or before 1-based ``iteration``."""
    last = min(iteration, refine_until - 1)
    if last <= refine_from:
        return 0
    return max(0, last // refine_every - refine_from // refine_every)


def growth_target(n: int, step: int, steps: int, seed: int | None, cap: int, growth: float = GROWTH) -> int:
    """The Gaussian count after the add of refine step ``step`` (1-based) of ``steps``.

    gsplat's rule is min(cap, int((1 + growth) n)). Given the seed's size, where that rule
    cannot take the seed to the cap within the window (seed (1 + growth)^steps < cap; under 20
    Gaussians it never grows at all), the count is at least the geometric path from the seed to
    the cap, ceil(seed (cap / seed)^(step / steps)), which reaches the cap at the last step.

    Args:
        n: the count before the add (after relocation; relocation keeps it).
        step, steps: this refine step's index and the window's number of refine steps.
        seed: the seed's count (None: gsplat's rule alone).
        cap: the most Gaussians additions may reach.

    Returns:
        the target count (n or more, unless n is already over the cap: then n).
    """
    target = int((1.0 + growth) * n)
    if seed is not None and 0 < seed < cap and steps > 0 and seed * (1.0 + growth) ** steps < cap:
        path = math.ceil(seed * (cap / seed) ** (min(step, steps) / steps) - 1e-9)
        target = max(target, path)
    return max(n, min(cap, target))


@dataclass
class MCMCStrategy(Strategy):
    """The MCMC refine schedule and cap (:class:`splat_train.strategy.base.Strategy`), made by its
    config (:class:`splat_train.strategy.configs.MCMCStrategyConfig`).

    Attributes:
        refine_from, refine_until, refine_every: relocate and add at iterations it with
            refine_from < it < refine_until and it % refine_every == 0 (1-based; gsplat's test,
            the config's densify_* schedule keys).
        cap: the Gaussian count never grows past this by additions (relocation keeps the count);
            a seed already larger keeps its size (nothing is removed; only relocation runs).
        min_opacity: a Gaussian at or below this opacity is dead (the config's prune_opacity).
        noise_lr: noise scale per unit of position learning rate (gsplat's 5e5).
        growth: new Gaussians per refine step as a fraction of the count (:data:`GROWTH`).
        seed_size: the seed's count, for :func:`growth_target`'s path to the cap (None:
            gsplat's 5 % alone, the config's ``mcmc_growth`` "gsplat").
    """

    refine_from: int
    refine_until: int
    refine_every: int
    cap: int
    min_opacity: float
    noise_lr: float
    growth: float = GROWTH
    seed_size: int | None = None

    name: ClassVar[str] = "mcmc"

    @classmethod
    def from_config(cls, cfg, max_gaussians: int | None = None, seed_size: int | None = None,
                    **overrides) -> "MCMCStrategy":
        """The strategy of :class:`splat_train.config.TrainConfig` ``cfg`` (its schedule and its
        mcmc settings), capped at ``max_gaussians`` (required: MCMC grows to its cap);
        ``seed_size`` (the seed's count) is kept where ``cfg.mcmc_growth`` is "reach_cap"."""
        return cfg.growth.mcmc.build(cfg.growth, cfg.schedule(), max_gaussians, seed_size, **overrides)

    @staticmethod
    def init_state(n: int, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
        """Running totals (0-d int64): Gaussians relocated and added so far. ``n`` is unused
        (the interface of :meth:`DensifyStrategy.init_state`)."""
        return {"relocated": torch.zeros((), dtype=torch.int64, device=device),
                "added": torch.zeros((), dtype=torch.int64, device=device)}

    def wants_stats(self, iteration: int) -> bool:
        """False: MCMC reads no render statistics (the trainer's render skips them)."""
        return False

    def update_state(self, state: dict[str, torch.Tensor], means2d_grad: torch.Tensor, radii: torch.Tensor,
                     visible: torch.Tensor, width: int, height: int, iteration: int) -> None:
        """Nothing to accumulate: MCMC needs no view-space gradient statistics."""

    def totals(self, state: dict[str, torch.Tensor]) -> dict[str, int]:
        """Gaussians relocated and added so far (``train.json`` ``strategy_totals``)."""
        return {k: int(v) for k, v in state.items()}

    def step(self, params: Params, optimizer: torch.optim.Optimizer, state: dict[str, torch.Tensor],
             iteration: int, extent: float, generator: torch.Generator | None = None) -> dict[str, int]:
        """After the optimiser step of 1-based ``iteration``: relocate then add when the
        schedule says so, then inject position noise scaled by the optimiser's current position
        rate. ``extent`` is unused (the rate already carries it).

        Returns counts {"relocated", "added"} (zeros when no refine ran)."""
        out = {"relocated": 0, "added": 0}
        if self.refine_from < iteration < self.refine_until and iteration % self.refine_every == 0:
            with torch.no_grad():
                dead = torch.sigmoid(params["opacity"].detach()) <= self.min_opacity
                out["relocated"] = relocate(params, optimizer, dead, self.min_opacity, generator)
                n = params["means"].shape[0]
                steps = refine_steps(self.refine_from, self.refine_until, self.refine_every, self.refine_until)
                step = refine_steps(self.refine_from, self.refine_until, self.refine_every, iteration)
                n_new = growth_target(n, step, steps, self.seed_size, self.cap, self.growth) - n
                out["added"] = sample_add(params, optimizer, n_new, self.min_opacity, generator)
            state["relocated"] += out["relocated"]
            state["added"] += out["added"]
            log.debug("it %d: relocated %d, added %d -> %d Gaussians", iteration, out["relocated"],
                      out["added"], params["means"].shape[0])
        lr = next(g["lr"] for g in optimizer.param_groups if g.get("name") == "means")
        inject_noise(params, float(lr) * self.noise_lr, generator)
        return out
