"""The 3DGS optimisation loop (docs/reference.md section 3) with checkpoints, resume and outputs.

One iteration (1-based ``it``): set the position rate (exponential decay x scene extent), pick
the next training view from a shuffled stack (refilled with a new permutation when empty, as
3DGS does), choose the background (fixed, or uniform random), render at the active SH degree
(+1 every ``sh_increase_every``), loss (1 - 0.2) L1 + 0.2 (1 - SSIM), backward, accumulate the
view-space gradient statistics, Adam step of the Gaussians, the held-out evaluation when due,
then densify / prune / reset opacity when the schedule says so (:mod:`splat_train.strategy.densify`), or
with the ``mcmc`` strategy relocate / add and inject position noise (:mod:`splat_train.strategy.mcmc`),
then the checkpoint when due.

The config's regularisers and extra optimisations are training parts
(:mod:`splat_train.parts.base`, each made by its config in ``cfg.parts``,
:func:`splat_train.parts.recipe_parts`), called only through their interface, whose hooks
the iteration runs in the list's order: the view's camera (pose refinement), a map of the
opacities of the training render (Gaussian dropout), loss terms added after the photometric
loss (depth prior, opacity / scale regularisers), and a step after the Gaussians' Adam step
(the pose corrections' Adam, their rate ramped by :func:`splat_train.parts.pose.pose_lr_factor` and
their scale gauge restored). Each part's state is in every checkpoint.

All randomness comes from one ``torch.Generator`` seeded with ``cfg.seed``; its state is in
every checkpoint, so on CPU a run resumed from ``DIR/ckpt`` ends with exactly the model of an
uninterrupted run. The held-out evaluation scores PSNR, SSIM and, with ``eval_lpips``, LPIPS-alex
(:mod:`splat_train.training.heldout`); its time is ``eval_time_s``, outside ``wall_time_s``, as is
a C++ kernel's one-time build (``kernel_build_s``; ``python -m splat_train.render.cpu.build`` builds
them ahead).
Outputs (docs/contracts.md): ``model.ply``, ``log.parquet``, ``ckpt/``,
``renders/``, ``train.json`` and, with pose refinement, ``cameras_refined/`` (COLMAP text);
with ``snapshot_every`` N, ``snapshot.ply`` every N iterations and at the last
(:mod:`splat_train.training.snapshot`, outside the training time).

What a run resolves from its config and inputs is resolved once (:class:`ResolvedRun`,
:func:`resolve_run`): the schedule, the background colour (the training images' mean read from
the images loaded for training), the depth prior it uses and the inputs digest.

Every checkpoint holds :func:`inputs_digest` (SHA-256 of the seed PLY's bytes, the decoded
training images and cameras, and the result-changing config); a run resumes only from a
checkpoint of the same digest. With ``resume_dir`` (the workflow's ``--resume-dir``) the
checkpoints live in ``resume_dir/<digest>/ckpt`` instead of ``out/ckpt``, outside the job's
outputs: a rerun with other inputs never finds a stale one, and the folder is removed once
the outputs are written.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch

from camio import Camera
from runtime.atomic import write_json
from camio.colmap import write_text_model
from camio.depth_prior import DEPTH_PRIOR_FILE
from camio.ply import read_gaussian_ply, write_gaussian_ply
from runtime.logs import peak_rss_mb, progress
from splat_train.training import checkpoint as ckpt
from splat_train.config import BACKGROUND_MEAN, POSE_KEYS, RESUME_FREE_KEYS, Schedule, TrainConfig, resolve_device
from splat_train.tree import added_at_default
from splat_train.render.cpu import raster as cpu_raster
from splat_train.data import View, load_views, load_views_on_mean, mean_colour, read_name_list, scene_extent
from splat_train.export import camera_tensors, render_params, render_views
from splat_train.gaussians import adam_step, make_optimizer, params_from_cloud, params_to_cloud, position_lr
from splat_train.training.heldout import LPIPS_NET, HeldoutScorer, unmeasured
from splat_train.losses import TrainingLoss
from splat_train.parts.compose import opacity_map, recipe_parts
from splat_train.render.rasterize import SKEW_ERROR, resolve_backend
from splat_train.rng import uniform
from splat_train.render.cpu.build import build_seconds
from splat_train.training.runlog import RunLog
from splat_train.training.snapshot import check_snapshot_every, write_snapshot

__all__ = ["train", "TrainResult", "NonFiniteLossError", "Trainer", "ResolvedRun", "resolve_run", "inputs_digest",
           "seed_depth_prior"]

log = logging.getLogger(__name__)

# Iterations between host reads of the training scalars (loss, L1, SSIM, MSE) on an
# accelerator: each read waits for the device's queue to drain. On the CPU a read costs
# nothing and the run reads every iteration (exact stop at a non-finite loss, before its
# backward pass). Evaluation, checkpoint and log iterations read too, so their rows are exact.
SYNC_EVERY = 10


def host_sync_every(device: torch.device) -> int:
    """Iterations between host reads of the training scalars on ``device`` (see SYNC_EVERY)."""
    return 1 if device.type == "cpu" else SYNC_EVERY


class NonFiniteLossError(RuntimeError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


@dataclass
class TrainResult:
    """Summary of a finished run (the content of ``train.json``)."""

    out_dir: Path
    summary: dict[str, Any]

    @property
    def model_path(self) -> Path:
        return self.out_dir / "model.ply"


def with_background(cfg: TrainConfig, colour: list[float]) -> TrainConfig:
    """``cfg`` with the background ``colour`` (RGB in [0, 1])."""
    return replace(cfg, optim=replace(cfg.optim, background=list(colour)))


def resolve_mean_background(cfg: TrainConfig, views: list[View]) -> TrainConfig:
    """``cfg`` with its ``background`` "mean" replaced by the views' mean colour
    (:func:`splat_train.data.mean_colour`); any other config as it is."""
    return with_background(cfg, mean_colour(views)) if cfg.optim.background == BACKGROUND_MEAN else cfg


def inputs_digest(seed_ply: str | Path, train_views: list[View], cfg: TrainConfig,
                  depth_prior: str | Path | None = None) -> str:
    """SHA-256 (hex) of what decides a run's result: the seed PLY's bytes (and the depth
    prior's, when one is used), each training view's name, camera (size, K, cam_from_world)
    and decoded pixels, and the config without the keys that may change on resume
    (:data:`RESUME_FREE_KEYS`), its ``background`` "mean" resolved from the views as the
    Trainer resolves it."""
    cfg = resolve_mean_background(cfg, train_views)
    h = hashlib.sha256()
    h.update(Path(seed_ply).read_bytes())
    if depth_prior is not None:
        h.update(b"depth_prior")
        h.update(Path(depth_prior).read_bytes())
    for v in train_views:
        cam = v.camera
        h.update(f"{v.name}|{cam.width}|{cam.height}".encode())
        h.update(np.ascontiguousarray(cam.K, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(cam.cam_from_world, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(v.image).tobytes())
    flat = cfg.to_flat()
    skip = {*RESUME_FREE_KEYS, *added_at_default(flat)}  # a part added since, off: the digest stays
    kept = {k: v for k, v in flat.items() if k not in skip}
    h.update(json.dumps(kept, sort_keys=True, default=str).encode())
    return h.hexdigest()


@dataclass(frozen=True)
class ResolvedRun:
    """What one run resolves from its config and inputs, once (:func:`resolve_run`).

    Attributes:
        cfg: the config, its ``background`` a colour (the mean resolved).
        schedule: the iteration counts of the run (:meth:`TrainConfig.schedule`).
        background_from: "set", or "mean" (the colour is the training images' mean).
        depth_prior: the depth prior the run uses (None: none, or no part reads one).
        digest: :func:`inputs_digest` of the run.
    """

    cfg: TrainConfig
    schedule: Schedule
    background_from: str
    depth_prior: Path | None
    digest: str


def resolve_run(cfg: TrainConfig, seed_ply: str | Path, train_views: list[View], depth_prior: str | Path | None = None,
                digest: str | None = None, background_from: str = "set") -> ResolvedRun:
    """The :class:`ResolvedRun` of ``cfg`` on ``seed_ply`` and ``train_views``: the background
    "mean" resolved from the views (:func:`splat_train.data.mean_colour`), ``depth_prior`` kept
    when a part of the config reads one, the schedule, and the digest (computed unless given)."""
    if cfg.optim.background == BACKGROUND_MEAN:
        cfg, background_from = resolve_mean_background(cfg, train_views), BACKGROUND_MEAN
    prior = Path(depth_prior) if depth_prior is not None and cfg.reads_depth_prior() else None
    return ResolvedRun(cfg, cfg.schedule(), background_from, prior,
                       digest or inputs_digest(seed_ply, train_views, cfg, prior))


def _device(name: str) -> torch.device:
    name = resolve_device(name)
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but torch sees no CUDA GPU; use --device cpu "
                           "or install a CUDA build of torch")
    dev = torch.device(name)
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise RuntimeError(f"device {name!r} requested but torch sees {torch.cuda.device_count()} CUDA GPU(s) "
                           "(indices from 0; CUDA_VISIBLE_DEVICES renumbers them)")
    return dev


class Trainer:
    """State of one run; :meth:`run` trains to ``cfg.iterations`` and writes the outputs."""

    def __init__(self, cfg: TrainConfig, seed_ply: str | Path, train_views: list[View], out_dir: str | Path,
                 test_views: list[View] | None = None, ckpt_dir: str | Path | None = None,
                 digest: str | None = None, depth_prior: str | Path | None = None,
                 background_from: str = "set", snapshot_every: int | None = None,
                 resolved: ResolvedRun | None = None) -> None:
        if not train_views:
            raise ValueError("no training views")
        self.snapshot_every = check_snapshot_every(snapshot_every)  # None: no snapshot.ply
        # once per run: the background colour, the schedule, the depth prior, the digest
        run = resolved or resolve_run(cfg, seed_ply, train_views, depth_prior, digest, background_from)
        cfg = run.cfg
        self.cfg, self.out = cfg, Path(out_dir)
        self.ckpt_dir = Path(ckpt_dir) if ckpt_dir is not None else self.out  # holds ckpt/
        self.depth_prior_path, self.digest, self.sched = run.depth_prior, run.digest, run.schedule
        train_pixels = sum(v.camera.width * v.camera.height for v in train_views)
        self.dev = _device(cfg.run.device)
        if self.dev.type == "cuda":  # train.json's peak_cuda_mb is this run's, not the process's
            torch.cuda.reset_peak_memory_stats(self.dev)
        self.backend = resolve_backend(cfg.run.rasterizer, self.dev)
        log.info("rasterizer backend: %s (config %r, device %s)", self.backend, cfg.run.rasterizer, self.dev)
        for part in cfg.parts:  # before anything is read: a part that cannot run on this backend
            part.check_backend(self.backend)
        self.train_views, self.test_views = train_views, test_views or []
        for v in [*self.train_views, *self.test_views]:  # once here: rasterize checks CPU tensors only
            if float(v.camera.K[0, 1]) != 0.0:
                raise ValueError(f"view {v.name!r}: {SKEW_ERROR}")
        self.targets = [torch.as_tensor(v.image, device=self.dev) for v in train_views]
        self.cams = [camera_tensors(v.camera, self.dev) for v in train_views]
        self.bg = torch.tensor(cfg.optim.background, dtype=torch.float32, device=self.dev)
        self.background_from = run.background_from  # "set", or "mean" (resolved to cfg's background)
        self.photometric = TrainingLoss(cfg.optim.lambda_dssim, self.dev)  # a CUDA graph on CUDA
        self.gen = torch.Generator().manual_seed(int(cfg.run.seed))
        cloud = read_gaussian_ply(seed_ply)
        self.extent = scene_extent([v.camera for v in train_views],
                                   cloud.means if cfg.run.extent_from_points else None)
        if len(cloud) == 0:
            raise ValueError(f"seed {seed_ply} holds 0 Gaussians: nothing can be trained or densified; "
                             "check the Bridge output (bridge.json counts) or its filters")
        # the cap and the strategy: a seed over the cap may raise it (seed_over_cap)
        self.seed_gaussians = len(cloud)
        self.max_gaussians = cfg.growth.max_gaussians_for(train_pixels, len(cloud))
        self.strategy_name = cfg.growth.strategy_for(train_pixels, len(cloud))
        log.info("recipe %s: strategy %s; schedule %s; growth cap %s (%d training pixels, seed %d, "
                 "seed over the cap: %s); parts %s",
                 cfg.recipe, self.strategy_name,
                 {k: f"{v} ({self.sched.source[k]})" for k, v in self.sched.to_dict().items() if k != "source"},
                 self.max_gaussians or "none", train_pixels, len(cloud), cfg.growth.seed_over_cap,
                 [c for c in cfg.parts if c.active()] or "none")
        self.strategy = cfg.growth.build(self.strategy_name, self.sched, self.max_gaussians, len(cloud))
        self.params = params_from_cloud(cloud, cfg.optim.sh_degree, self.dev)
        self.optimizer = make_optimizer(self.params, cfg, self.extent)
        self.state = self.strategy.init_state(len(self.params["means"]), self.dev)
        self.scorer = (HeldoutScorer(cfg.run.eval_lpips, cfg.run.lpips_weights, self.dev)
                       if self.test_views else None)
        self.render_state: tuple[int, torch.Tensor] = (0, self.bg)  # this iteration's SH degree, background
        self.parts = recipe_parts(cfg, train_views, [c[0] for c in self.cams], self.gen, self.depth_prior_path,
                                  targets=self.targets, renderer=self, schedule=self.sched)
        log.info("training parts: %s", ", ".join(p.name for p in self.parts) or "none")
        self.need_depth = any(p.needs_depth for p in self.parts)  # else gsplat renders colour only
        # the parts whose cameras replace the given ones (pose refinement)
        self.moves_cameras = any(p.moves_cameras for p in self.parts)
        self.stack: list[int] = []
        self.log = RunLog()
        self.iteration, self.wall, self.resumed_from = 0, 0.0, None
        # log rows whose scalars are still on the device (see flush); on a GPU every read of
        # one waits for the queued work, so they are read SYNC_EVERY iterations at a time
        self.pending: list[dict[str, Any]] = []
        self.sync_every = host_sync_every(self.dev)
        self.last_view = 0

    # ---------------------------------------------------------------- checkpoints
    def payload(self) -> dict[str, Any]:
        return {
            "params": {k: p.detach().clone() for k, p in self.params.items()},
            "optimizer": self.optimizer.state_dict(),
            "strategy_state": {k: v.clone() for k, v in self.state.items()},
            "parts": {p.name: s for p in self.parts if (s := p.state_dict()) is not None},
            "rng": self.gen.get_state(),
            "view_stack": torch.tensor(self.stack, dtype=torch.int64),
            "train_names": [v.name for v in self.train_views],
            "log": self.log.state_dict(),
            "wall_time_s": float(self.wall),
            "config": self.cfg.to_dict(),
            "inputs_sha256": self.digest,
        }

    def restore(self, path: Path) -> None:
        """Continue from checkpoint ``path`` (its config and training views must match)."""
        data = ckpt.load_checkpoint(path, self.dev)
        old, new = data["config"], self.cfg.to_dict()
        free = {*RESUME_FREE_KEYS, *(added_at_default(new) - set(old))}  # a part added since, off
        if not new["pose_refine"] and not old.get("pose_refine"):
            free |= set(POSE_KEYS)  # unused without refinement (and absent from older checkpoints)
        diff = sorted(k for k in new if k not in free and old.get(k) != new[k])
        if diff:
            raise ValueError(f"cannot resume from {path}: its config differs in {diff} "
                             f"({ {k: old.get(k) for k in diff} } vs { {k: new[k] for k in diff} }); "
                             "use another --out or delete its ckpt/ folder to start again")
        if list(data["train_names"]) != [v.name for v in self.train_views]:
            raise ValueError(f"cannot resume from {path}: it was trained on other images; use another --out")
        if data.get("inputs_sha256") != self.digest:
            raise ValueError(f"cannot resume from {path}: it was trained from other inputs (seed, cameras or "
                             f"images; inputs hash {data.get('inputs_sha256')} vs {self.digest}); "
                             "use another --out or delete its ckpt/ folder to start again")
        self.params = {k: torch.nn.Parameter(v.to(self.dev)) for k, v in data["params"].items()}
        self.optimizer = make_optimizer(self.params, self.cfg, self.extent)
        self.optimizer.load_state_dict(data["optimizer"])
        self.state = {k: v.to(self.dev) for k, v in data["strategy_state"].items()}
        # checkpoints written before the parts kept the pose corrections' state under "pose"
        states = data["parts"] if "parts" in data else {"pose": data.get("pose")}
        for part in self.parts:
            if part.state_dict() is not None:
                part.load_state_dict(states[part.name])
        self.gen.set_state(data["rng"])
        self.stack = [int(x) for x in data["view_stack"].tolist()]
        self.log.load_state_dict(data["log"])
        self.wall = float(data["wall_time_s"])
        self.iteration = int(data["iteration"])
        self.resumed_from = str(path)
        log.info("resumed from %s at iteration %d (%d Gaussians)", path, self.iteration, self.num_gaussians)

    def save(self) -> Path:
        bad = [k for k, p in self.params.items() if not torch.isfinite(p).all()]
        if bad:
            raise NonFiniteLossError(f"non-finite parameters {bad} at iteration {self.iteration}; "
                                     f"not checkpointed; last good: {ckpt.latest_checkpoint(self.ckpt_dir)}")
        return ckpt.save_checkpoint(self.ckpt_dir, self.iteration, self.payload(), self.cfg.keep_checkpoints)

    # ---------------------------------------------------------------- training
    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    def next_view(self) -> int:
        if not self.stack:
            self.stack = torch.randperm(len(self.train_views), generator=self.gen).tolist()
        return self.stack.pop()

    def view_camera(self, idx: int) -> tuple[torch.Tensor, torch.Tensor]:
        """[4, 4] cam_from_world (world -> OpenCV camera) and [3, 3] K (pixels) that training
        view ``idx`` is rendered with at the current iteration: the given ones, through every
        part's :meth:`~splat_train.parts.base.TrainPart.camera` (refined with pose refinement)."""
        cw, K = self.cams[idx]
        for part in self.parts:
            cw, K = part.camera(self.iteration, idx, cw, K)
        return cw, K

    def refined_cameras(self) -> list[torch.Tensor]:
        """[4, 4] cam_from_world per training view (refined when pose refinement is on)."""
        with torch.no_grad():
            return [self.view_camera(i)[0].detach() for i in range(len(self.train_views))]

    def refined_intrinsics(self) -> list[torch.Tensor]:
        """[3, 3] K per training view (refined with focal refinement)."""
        with torch.no_grad():
            return [self.view_camera(i)[1].detach() for i in range(len(self.train_views))]

    def render_rgb(self, cam_from_world: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
        """[H, W, 3] differentiable render of the model into a camera ([4, 4] cam_from_world, [3, 3]
        K in pixels) at this iteration's SH degree and background, without dropout and without
        densification statistics (:class:`splat_train.parts.base.ViewRenderer`)."""
        deg, bg = self.render_state
        return render_params(self.params, deg, cam_from_world, K, width, height, bg, self.backend,
                             depth=False, stats=False)["rgb"]

    def step(self) -> torch.Tensor:
        """One optimisation iteration (``self.iteration`` is advanced first).

        Returns:
            [4] (loss, L1, SSIM, MSE of the render) on the training device, detached: reading
            them is a device sync, which :meth:`run` does once every ``sync_every`` iterations
            (:meth:`flush`). With ``sync_every == 1`` a non-finite loss raises here, before
            the backward pass; otherwise at the next flush.
        """
        self.iteration += 1
        it, cfg = self.iteration, self.cfg
        optim = cfg.optim
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = position_lr(cfg, it, self.extent)
        deg = self.sched.sh_degree_at(it, optim.sh_degree)
        idx = self.last_view = self.next_view()
        bg = uniform(3, self.gen, self.dev) if optim.random_background else self.bg
        self.render_state = (deg, bg)
        cam = self.train_views[idx].camera
        cam_from_world, K = self.view_camera(idx)
        want_stats = self.strategy.wants_stats(it)  # densification statistics still read
        out = render_params(self.params, deg, cam_from_world, K, cam.width, cam.height, bg, self.backend,
                            opacity_fn=opacity_map(self.parts, it), depth=self.need_depth, stats=want_stats)
        loss, stats = self.photometric(out["rgb"], self.targets[idx])  # stats: L1, SSIM, MSE
        for part in self.parts:
            term = part.loss(it, idx, out, self.params)
            if term is not None:
                loss = loss + term
        if self.sync_every == 1 and not torch.isfinite(loss.detach()):
            self._non_finite(float(loss.detach()), it, cam.name)  # before the step moves anything
        loss.backward()
        if want_stats and out["means2d"].grad is not None:
            # [N, 2] in pixels for every backend (the rasterize contract; the gsplat adapter too)
            self.strategy.update_state(self.state, out["means2d"].grad, out["radii"], out["visible"],
                                       cam.width, cam.height, it)
        adam_step(self.optimizer)  # fused kernel on a GPU, the C++ kernel's threads on the CPU
        self.optimizer.zero_grad(set_to_none=True)
        for part in self.parts:
            part.after_step(it, self.params)
        return torch.cat([loss.detach().reshape(1), stats])

    def _non_finite(self, loss: float, it: int, view: str) -> NoReturn:
        last = ckpt.latest_checkpoint(self.ckpt_dir)
        raise NonFiniteLossError(
            f"loss is {loss} at iteration {it} (view {view!r}); the run stops. "
            f"Last good checkpoint: {last or 'none (no checkpoint written yet)'}. Lower the "
            "learning rates or check the seed PLY / cameras for extreme values.")

    def flush(self) -> None:
        """Move the pending iterations' scalars to the host (one device sync) and append their
        rows to the run log, in order; a non-finite loss raises :class:`NonFiniteLossError`
        naming the first such iteration (its row and the later ones are not logged)."""
        if not self.pending:
            return
        vals = torch.stack([p.pop("scalars") for p in self.pending]).cpu().double().tolist()
        rows, self.pending = self.pending, []
        for row, (loss, l1, s, mse) in zip(rows, vals):
            view = row.pop("view")
            if not math.isfinite(loss):
                self._non_finite(loss, int(row["iteration"]), view)
            self.log.append(loss=loss, l1=l1, ssim=s, train_psnr=-10 * math.log10(max(mse, 1e-20)), **row)

    def _sync(self) -> None:
        if self.dev.type == "cuda":
            torch.cuda.synchronize(self.dev)

    def evaluate(self, views: list[View], out_dir: Path | None = None, refined: bool = False,
                 scorer: HeldoutScorer | None = None) -> float:
        """Mean PSNR over ``views`` at the current SH degree (NaN without views); with
        ``scorer``, every render is also scored by it (SSIM, LPIPS: :meth:`evaluate_heldout`)."""
        if not views:
            return float("nan")
        deg = self.sched.sh_degree_at(max(self.iteration, 1), self.cfg.optim.sh_degree)
        override = self.refined_cameras() if refined and self.moves_cameras else None
        k_override = self.refined_intrinsics() if refined and self.moves_cameras else None
        scores = render_views(self.params, deg, views, self.bg, out_dir, override, desc="evaluate",
                              K_override=k_override, backend=self.backend, on_render=scorer)
        return float(np.mean(list(scores.values()))) if scores else float("nan")

    def evaluate_heldout(self) -> dict[str, float]:
        """Mean held-out PSNR, SSIM, LPIPS (NaN when off or absent), coverage and PSNR where
        covered over the test views: the ``test_*`` columns of log.parquet
        (:mod:`splat_train.training.heldout`)."""
        if self.scorer is None:
            return unmeasured()
        self.scorer.reset()
        self.evaluate(self.test_views, scorer=self.scorer)
        return self.scorer.means()

    def run(self) -> TrainResult:
        cfg = self.cfg
        latest = ckpt.latest_checkpoint(self.ckpt_dir)
        if latest is not None:
            self.restore(latest)
        t_start = time.perf_counter()
        eval_time = 0.0
        every_log = max(1, cfg.iterations // 10)
        bar = progress(range(self.iteration + 1, cfg.iterations + 1), total=cfg.iterations - self.iteration,
                       desc="train")
        for _ in bar:
            t0, b0 = time.perf_counter(), build_seconds()
            scalars = self.step()
            it = self.iteration
            evaluate = bool(self.test_views) and cfg.eval_every > 0 and (
                it % cfg.eval_every == 0 or it == cfg.iterations)
            if evaluate:
                self._sync()  # this iteration's queued GPU work is training time, not evaluation
            # a kernel's one-time build (first use in this process) is not training time
            self.wall += time.perf_counter() - t0 - (build_seconds() - b0)
            held = unmeasured()
            if evaluate:
                te = time.perf_counter()
                held = self.evaluate_heldout()
                eval_time += time.perf_counter() - te
            test_psnr = held["psnr"]
            # densify / prune / opacity reset after the held-out evaluation, as 3DGS orders its
            # loop: a test PSNR logged at a reset iteration measures the model, not the reset
            t0 = time.perf_counter()
            self.strategy.step(self.params, self.optimizer, self.state, it, self.extent, self.gen)
            self.wall += time.perf_counter() - t0
            self.pending.append(dict(iteration=it, wall_time_s=self.wall, num_gaussians=self.num_gaussians,
                                     test_psnr=test_psnr, test_ssim=held["ssim"], test_lpips=held["lpips"],
                                     test_coverage=held["coverage"], test_psnr_covered=held["psnr_covered"],
                                     test_ssim_covered=held["ssim_covered"], test_lpips_covered=held["lpips_covered"],
                                     view=self.train_views[self.last_view].name, scalars=scalars))
            saving = it % cfg.checkpoint_every == 0 or it == cfg.iterations
            if it % self.sync_every == 0 or it % every_log == 0 or saving or evaluate:
                t0 = time.perf_counter()
                self.flush()  # before any checkpoint: a non-finite loss stops the run first
                self.wall += time.perf_counter() - t0
            rows = self.log.rows  # this iteration's row is in it once flushed
            if (it % 10 == 0 or it == cfg.iterations) and not self.pending:
                bar.set_postfix(loss=f"{rows['loss'][-1]:.4f}", psnr=f"{rows['train_psnr'][-1]:.2f}",
                                n=self.num_gaussians)
            if it % every_log == 0:  # flushed above
                log.info("it %d/%d loss %.4f psnr %.2f n %d%s%s (%.2f it/s)", it, cfg.iterations, rows["loss"][-1],
                         rows["train_psnr"][-1], self.num_gaussians,
                         "" if math.isnan(test_psnr) else f" test psnr {test_psnr:.2f} ssim {held['ssim']:.4f}",
                         "" if math.isnan(held["lpips"]) else f" lpips {held['lpips']:.4f}",
                         it / max(self.wall, 1e-9))
            if saving:
                self.save()
                self.log.write_parquet(self.out / "log.parquet")
            if self.snapshot_every and (it % self.snapshot_every == 0 or it == cfg.iterations):
                write_snapshot(self.out, params_to_cloud(self.params), it)
        return self.finish(time.perf_counter() - t_start, eval_time)

    def finish(self, session_s: float, eval_time: float) -> TrainResult:
        """Write model.ply, log.parquet, renders/, train.json (and cameras_refined/)."""
        out, cfg = self.out, self.cfg
        write_gaussian_ply(out / "model.ply", params_to_cloud(self.params))
        self.log.write_parquet(out / "log.parquet")
        render_set = self.test_views if self.test_views else self.train_views
        test_psnr = self.evaluate(self.test_views, out / "renders") if self.test_views else float("nan")
        train_psnr = self.evaluate(self.train_views, None if self.test_views else out / "renders", refined=True)
        if self.moves_cameras:
            # at the training image size; K is the refined one where a part moves it (focal refinement)
            moves_k = any(p.moves_intrinsics for p in self.parts)
            cams = [Camera(v.name, v.camera.width, v.camera.height,
                           (K.cpu().double().numpy() if moves_k else v.camera.K),
                           cw.cpu().double().numpy()[:3])
                    for v, cw, K in zip(self.train_views, self.refined_cameras(), self.refined_intrinsics())]
            write_text_model(out / "cameras_refined", cams)
        summary = {
            "iterations": cfg.iterations, "wall_time_s": self.wall, "session_time_s": session_s,
            "eval_time_s": eval_time, "kernel_build_s": build_seconds(), "num_gaussians": self.num_gaussians,
            "train_psnr": train_psnr, "test_psnr": test_psnr,
            "num_train_views": len(self.train_views), "num_test_views": len(self.test_views),
            "rendered": [v.name for v in render_set], "scene_extent": self.extent,
            "peak_rss_mb": peak_rss_mb(),
            "peak_cuda_mb": (torch.cuda.max_memory_allocated() / 2**20 if self.dev.type == "cuda" else None),
            "device": str(self.dev), "rasterizer": self.backend, "torch_threads": torch.get_num_threads(),
            "resumed_from": self.resumed_from, "inputs_sha256": self.digest, "schedule": self.sched.to_dict(),
            "recipe": cfg.recipe, "seed_gaussians": self.seed_gaussians, "max_gaussians": self.max_gaussians,
            "strategy": self.strategy_name,
            # running totals of the mcmc strategy (relocated, added); {} for densify's per-row statistics
            "strategy_totals": self.strategy.totals(self.state),
            "depth_prior": None,  # the depth part's entry below when it runs
            "config": cfg.to_dict(), "background_from": self.background_from,
            "test_curve": self.log.test_curve(),
            "heldout_lpips": {"enabled": bool(cfg.eval_lpips), "net": LPIPS_NET,
                              "weights": None if self.scorer is None else self.scorer.weights},
        }
        for part in self.parts:
            summary.update(part.summary())
        write_json(out / "train.json", summary)
        log.info("trained %d iterations in %.1f s (training time): %d Gaussians, train PSNR %.2f, "
                 "test PSNR %s -> %s", cfg.iterations, self.wall, self.num_gaussians, train_psnr,
                 "n/a" if math.isnan(test_psnr) else f"{test_psnr:.2f}", out)
        return TrainResult(out, summary)


def seed_depth_prior(seed: str | Path, cfg: TrainConfig, depth_prior: str | Path | None = None) -> Path | None:
    """The depth prior a run of ``cfg`` on ``seed`` uses: ``depth_prior`` when given, else the
    Bridge's file beside the seed when there is one; None when ``cfg`` has no depth term."""
    if not cfg.reads_depth_prior():
        return None
    if depth_prior is not None:
        return Path(depth_prior)
    beside = Path(seed).parent / DEPTH_PRIOR_FILE
    return beside if beside.is_file() else None


def _is_digest_folder(path: Path) -> bool:
    """A checkpoint folder this trainer wrote under a resume dir: 16 hex digits holding only
    ``ckpt/`` (anything else there is not the trainer's and is never deleted)."""
    return (path.is_dir() and not path.is_symlink() and len(path.name) == 16
            and all(c in "0123456789abcdef" for c in path.name)
            and all(child.name == "ckpt" for child in path.iterdir()))


def train(seed: str | Path, cameras: str | Path, images: str | Path, out_dir: str | Path,
          cfg: TrainConfig | None = None, test_cameras: str | Path | None = None,
          test_images: str | Path | None = None, image_list: str | Path | list[str] | None = None,
          test_image_list: str | Path | list[str] | None = None,
          resume_dir: str | Path | None = None, depth_prior: str | Path | None = None,
          snapshot_every: int | None = None) -> TrainResult:
    """Train 3DGS from a seed PLY and posed images; resume from ``out_dir/ckpt`` if present.

    Args:
        seed: 3DGS-layout PLY (the Bridge's seed.ply), world frame of ``cameras``.
        cameras: COLMAP model folder of the training cameras.
        images: folder of the training images (names as in the model).
        out_dir: output folder (docs/contracts.md, splat_train output).
        cfg: hyperparameters (defaults: :class:`TrainConfig`).
        test_cameras, test_images: held-out views in the same frame (both or neither).
        image_list: restrict training to these names (a file or a list).
        test_image_list: restrict the held-out views to these names (e.g. when the test
            cameras folder is the Bridge's folder of every camera).
        depth_prior: the Bridge's ``depth_prior.npz`` (None: the one beside ``seed``, if any);
            used when the config's ``depth_weight`` > 0.
        resume_dir: keep checkpoints in ``resume_dir/<inputs digest>/ckpt`` (not ``out_dir/ckpt``);
            checkpoint folders of other digests there are stale and removed at the start (any
            other file or folder there is left alone), this run's is
            removed after its outputs are written.
        snapshot_every: write ``out_dir/snapshot.ply`` every this many iterations and at the
            last (:mod:`splat_train.training.snapshot`; what ``python -m splat_train view`` follows);
            None: never.

    Raises:
        NonFiniteLossError: the loss became non-finite (the last checkpoint stays in ckpt/).
    """
    cfg = cfg or TrainConfig()
    check_snapshot_every(snapshot_every)
    if (test_cameras is None) != (test_images is None):
        raise ValueError("give both --test-cameras and --test-images, or neither")
    if cfg.run.num_threads > 0:
        torch.set_num_threads(cfg.run.num_threads)
    cpu_raster.set_kernel_threads(cfg.run.kernel_threads or len(os.sched_getaffinity(0)))
    names = read_name_list(image_list) if isinstance(image_list, (str, Path)) else image_list
    test_names = (read_name_list(test_image_list) if isinstance(test_image_list, (str, Path))
                  else test_image_list)
    t0 = time.perf_counter()
    background_from, downsample = "set", cfg.run.downsample
    if cfg.optim.background == BACKGROUND_MEAN:
        # each image read once, composited on black for the mean (RGBA ones again, on the mean)
        train_views, colour = load_views_on_mean(cameras, images, names, downsample)
        cfg, background_from = with_background(cfg, colour), BACKGROUND_MEAN
        log.info("background: the training images' mean colour (%.4f, %.4f, %.4f)", *colour)
    else:
        train_views = load_views(cameras, images, names, downsample, tuple(cfg.optim.background))
    bg = tuple(cfg.optim.background)
    test_views = (load_views(test_cameras, test_images, test_names, downsample, bg)
                  if test_cameras is not None else [])
    log.info("data loaded in %.1f s: %d training, %d test views", time.perf_counter() - t0,
             len(train_views), len(test_views))
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    run = resolve_run(cfg, seed, train_views, seed_depth_prior(seed, cfg, depth_prior), background_from=background_from)
    digest = run.digest
    if resume_dir is None:
        return Trainer(run.cfg, seed, train_views, out_dir, test_views, snapshot_every=snapshot_every,
                       resolved=run).run()
    resume_dir = Path(resume_dir)
    own = resume_dir / digest[:16]
    for stale in (p for p in resume_dir.iterdir() if p != own and _is_digest_folder(p)) if resume_dir.is_dir() else ():
        log.info("removing %s: checkpoints of other inputs or config", stale)
        shutil.rmtree(stale)
    result = Trainer(run.cfg, seed, train_views, out_dir, test_views, ckpt_dir=own, snapshot_every=snapshot_every,
                     resolved=run).run()
    shutil.rmtree(own, ignore_errors=True)
    try:
        resume_dir.rmdir()
    except OSError:
        pass
    return result
