"""The test-pose protocol: each held-out camera's pose optimised against its image, Gaussians frozen.

The strict protocol (docs/reference.md section 4) renders a held-out view at its reference pose mapped
into the model frame by the Sim(3) fitted on the training cameras, so every error of the
training poses is charged to the rendering. The test-pose protocol (InstantSplat's) starts from
that same pose and optimises a rigid correction of it alone against the test image:

    cam_from_world' = [exp(omega) | d * u] @ cam_from_world,

with (omega, u) a 6-vector initialised to zero (omega a rotation vector in radians, u a
translation in units of d, the median depth of the model's Gaussians in front of the starting
camera: :func:`scene_depth`), so one rate moves rotation and translation by comparable image
shifts on every scene. The loss is training's photometric loss
(:func:`splat_train.losses.photometric_loss`), Adam for a fixed number of steps
(:data:`DEFAULT_STEPS`) with its rate decayed exponentially from :data:`DEFAULT_LR` to
:data:`FINAL_LR_FRACTION` of it over the steps (:func:`testpose_lr`), so the pose settles
instead of oscillating at the rate's scale; the same for every method, recorded in the output.
Intrinsics and Gaussians never change. The pose kept is the one with the lowest loss seen (the
start included), so the correction never raises the loss against the test image.
``patience`` K (``--patience``, :data:`DEFAULT_PATIENCE`: off) ends a view after K steps in a row without a
new lowest loss; testpose.json records it and each view's ``steps_run``.

Gradients: the "cpu" backend keeps its fused C++ projection and takes the pose's gradient from
that kernel's backward (``rasterize(kernel_camera_grad=True)``, :mod:`splat_train.render.cpu.project`:
dL/d(cam_from_world) chained from the blend's means2d / conic / colour gradients, summed only over
the Gaussians the blend reached; the same values as autograd through the torch projection,
tests/test_train_testpose.py); the activations and SH pair are computed once per view. The
"torch" backend differentiates its torch projection; gsplat gives the gradient of the view matrix.

Cost on a CPU (AMD EPYC, AVX2, one thread as the workflow runs it, ``OMP_NUM_THREADS=1``, load
~1 on 2 cores; the demo's cells, 128x96, SH degree 3, 500 steps = 501 renders with their
backward per view): 7.3 s per view (14.5 ms per step) at 1.1k Gaussians, 7.2-9.1 s (14-18 ms)
at 2.2k, 32 s (64 ms) at 62k. At 1-2k Gaussians about half a step is the C++ kernels (blend
forward + backward ~3.7 ms, SSIM ~0.8 ms, projection + pose gradient ~0.6 ms) and half Python
and autograd dispatch; at 62k the kernels are ~50 of ~60 ms (projection forward 12, pose
gradient 8, blend forward + backward 17, footprints 9). Through the torch projection it was
11.2 s, 11.8-12.5 s and 91 s per view. Reproduce after ``make demo``, with
``R=results/synthetic/bundled`` and ``C=$R/n3/oracle/gated``::

    OMP_NUM_THREADS=1 python -m splat_train testpose --model $C/train/model.ply \\
        --cameras $C/align/sparse/0 --images $R/test_images --out work/tp

(``wall_time_s`` in ``work/tp/testpose.json``: 3 views, 501 renders each).
docs/protocols.md states what this costs the demo.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

from camio import Camera
from runtime.atomic import write_json
from camio.colmap import write_text_model
from camio.alpha import alpha_path, write_alpha
from camio.images import write_image
from camio.ply import read_gaussian_ply
from splat_train.data import View, load_views, read_name_list
from splat_train.export import background_note, camera_tensors, model_background, render_name, render_params
from splat_train.gaussians import activated, params_from_cloud
from splat_train.losses import photometric_loss, psnr
from splat_train.parts.pose import so3_exp
from splat_train.render.rasterize import rasterize, resolve_backend
from splat_train.recipes import BACKGROUND_BLACK

__all__ = ["DEFAULT_STEPS", "DEFAULT_PATIENCE", "DEFAULT_LR", "FINAL_LR_FRACTION", "testpose_lr", "PROTOCOL_NAME",
           "se3_correction", "scene_depth", "pose_change", "refine_test_pose", "run_testpose"]

log = logging.getLogger(__name__)

#: Adam steps per held-out view (InstantSplat's count), the same for every method.
DEFAULT_STEPS = 500
#: Steps in a row without a lower loss that end a view early; 0: every step is run.
DEFAULT_PATIENCE = 0
#: Adam rate of the rotation vector (radians) and the translation (units of the scene depth).
DEFAULT_LR = 1e-3
#: The rate at the last step as a fraction of the first (exponential decay between them).
FINAL_LR_FRACTION = 0.01
#: The protocol's name in every file, table and page.
PROTOCOL_NAME = "test-pose"


def testpose_lr(step: int, steps: int, lr: float = DEFAULT_LR) -> float:
    """Adam rate at 0-based ``step`` of ``steps``: lr * FINAL_LR_FRACTION ** (step / (steps - 1))."""
    if steps <= 1:
        return lr
    return lr * FINAL_LR_FRACTION ** (step / (steps - 1))


def se3_correction(delta: torch.Tensor, trans_scale: float) -> torch.Tensor:
    """The left correction [exp(omega) | trans_scale * u] of a 6-vector (omega, u).

    Args:
        delta: [6] (rotation vector in radians, translation in units of ``trans_scale``).
        trans_scale: world length of one translation unit.

    Returns:
        [4, 4] rigid transform acting on the camera frame (identity at delta = 0).
    """
    top = torch.cat([so3_exp(delta[:3]), trans_scale * delta[3:, None]], 1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=delta.dtype, device=delta.device)
    return torch.cat([top, bottom], 0)


def scene_depth(means: torch.Tensor, cam_from_world: torch.Tensor) -> float:
    """Median camera z of the Gaussians in front of a camera (1 when none is in front).

    Args:
        means: [N, 3] Gaussian centres (model frame).
        cam_from_world: [4, 4] world -> OpenCV camera.
    """
    z = (means @ cam_from_world[2, :3] + cam_from_world[2, 3]).detach()  # [N] camera z
    z = z[z > 0]
    return float(z.median()) if len(z) else 1.0


def pose_change(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """(rotation angle in degrees, camera-centre distance in world units) between two poses.

    Args:
        before, after: [3, 4] or [4, 4] cam_from_world (same world frame).
    """
    Ra, Rb = np.asarray(before)[:3, :3], np.asarray(after)[:3, :3]
    cos = (np.trace(Rb @ Ra.T) - 1.0) / 2.0
    ca = -Ra.T @ np.asarray(before)[:3, 3]
    cb = -Rb.T @ np.asarray(after)[:3, 3]
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0)))), float(np.linalg.norm(cb - ca))


def refine_test_pose(params: dict[str, torch.Tensor], sh_degree: int, cam_from_world: torch.Tensor,
                     K: torch.Tensor, target: torch.Tensor, steps: int = DEFAULT_STEPS, lr: float = DEFAULT_LR,
                     backend: str = "auto", lambda_dssim: float | None = None,
                     patience: int = DEFAULT_PATIENCE,
                     background: tuple[float, float, float] = BACKGROUND_BLACK) -> dict:
    """Optimise one camera's pose against its image with the Gaussians frozen (module docstring).

    Args:
        params: trainable-layout Gaussians (:mod:`splat_train.gaussians`), model frame; not changed.
        cam_from_world: [4, 4] starting pose (world -> OpenCV camera, model frame).
        K: [3, 3] intrinsics in the pixels of ``target``.
        target: [H, W, 3] test image in [0, 1] on the params' device.
        steps: Adam steps (0 keeps the start).
        lr: first Adam rate of (omega, u) (:func:`testpose_lr`).
        lambda_dssim: SSIM weight of the loss (training's default when None).
        patience: stop once this many steps in a row have not lowered the lowest loss seen (the
            rate schedule stays the one of ``steps``); 0 (the default): every step is run.
        background: RGB in [0, 1] behind the Gaussians (the one the model was trained against).

    Returns:
        ``cam_from_world`` [4, 4] the pose kept (detached), ``loss_start``, ``loss_end`` (of the pose
        kept), ``best_step`` (0 = the start), ``trans_scale``, ``delta`` [6] the correction kept
        (zeros at the start), ``steps_run`` (Adam steps taken: ``steps`` unless stopped early).
    """
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if patience < 0:
        raise ValueError(f"patience must be >= 0, got {patience}")
    if lambda_dssim is None:
        from splat_train.config import OptimConfig

        lambda_dssim = OptimConfig.lambda_dssim
    frozen = {k: v.detach() for k, v in params.items()}
    # what does not depend on the pose, once: activations and the SH pair
    scales, opacities, quats = activated(frozen)
    colors = (frozen["sh_dc"], frozen["sh_rest"])
    cw0 = cam_from_world.detach()
    height, width = int(target.shape[0]), int(target.shape[1])
    scale = scene_depth(frozen["means"], cw0)
    delta = torch.zeros(6, dtype=cw0.dtype, device=cw0.device, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=lr)
    bg = torch.tensor(background, dtype=torch.float32, device=cw0.device)
    best = (math.inf, cw0, 0, delta.detach().clone())
    loss_start = None
    steps_run = 0
    for step in range(steps + 1):
        steps_run = step
        cw = se3_correction(delta, scale) @ cw0
        out = rasterize(frozen["means"], quats, scales, opacities, colors, cw, K, width, height, background=bg,
                        sh_degree=sh_degree, backend=backend, kernel_camera_grad=True)
        loss, _, _ = photometric_loss(out["rgb"], target, lambda_dssim)
        value = float(loss.detach())
        if loss_start is None:
            loss_start = value
        if not math.isfinite(value):
            log.warning("non-finite test-pose loss at step %d: keeping the best pose so far", step)
            break
        if value < best[0]:
            best = (value, cw.detach().clone(), step, delta.detach().clone())
        if step == steps or (patience and step - best[2] >= patience):
            break
        opt.zero_grad(set_to_none=True)
        loss.backward()
        for g in opt.param_groups:
            g["lr"] = testpose_lr(step, steps, lr)
        opt.step()
    return {"cam_from_world": best[1], "loss_start": loss_start, "loss_end": best[0], "best_step": best[2],
            "trans_scale": scale, "delta": best[3], "steps_run": steps_run}


def run_testpose(model: str | Path, cameras: str | Path, images: str | Path, out_dir: str | Path,
                 steps: int = DEFAULT_STEPS, lr: float = DEFAULT_LR, device: str = "cpu",
                 backend: str = "auto", names: str | Path | None = None,
                 patience: int = DEFAULT_PATIENCE, alpha: bool = False) -> dict:
    """The test-pose protocol on a camera folder: refined cameras, renders and a record, against
    the background the model was trained against (:func:`splat_train.export.model_background`).

    Writes ``out_dir/sparse/0`` (COLMAP text: the refined held-out cameras, model frame, at the
    image sizes), ``out_dir/renders/<stem>.png`` (with ``alpha``, each render's accumulated
    opacity in ``out_dir/renders/alpha/<stem>.png`` too, :mod:`camio.alpha`) and ``out_dir/testpose.json``
    (docs/contracts.md).

    Returns:
        The ``testpose.json`` record.
    """
    t0 = time.perf_counter()
    name_list = read_name_list(names) if names is not None else None
    background, source = model_background(model)
    log.info("%s", background_note(background, source))
    views: list[View] = load_views(cameras, images, name_list, background=background)
    cloud = read_gaussian_ply(model)
    params = params_from_cloud(cloud, sh_degree=cloud.sh_degree, device=device)
    for p in params.values():
        p.requires_grad_(False)
    ran = resolve_backend(backend, device)
    out = Path(out_dir)
    refined: list[Camera] = []
    per_view = {}
    bg = torch.tensor(background, dtype=torch.float32, device=device)
    for v in views:
        cw, K = camera_tensors(v.camera, device)
        target = torch.as_tensor(v.image, device=device)
        res = refine_test_pose(params, cloud.sh_degree, cw, K, target, steps, lr, ran, patience=patience,
                               background=background)
        with torch.no_grad():
            before = render_params(params, cloud.sh_degree, cw, K, v.camera.width, v.camera.height, bg, ran)
            after = render_params(params, cloud.sh_degree, res["cam_from_world"], K, v.camera.width,
                                  v.camera.height, bg, ran)
        rgb = after["rgb"].clamp(0.0, 1.0)
        write_image(out / "renders" / render_name(v.name), rgb.cpu().numpy())
        if alpha:
            write_alpha(alpha_path(out / "renders", render_name(v.name)), after["alpha"].cpu().numpy())
        # the kept correction applied in float64 to the camera as read (the start itself when
        # best_step is 0), not the float32 pose the renders used: no float32 round trip in the
        # written cameras and the recorded pose change
        start = np.eye(4)
        start[:3] = v.camera.cam_from_world
        corr = se3_correction(res["delta"].detach().cpu().double(), res["trans_scale"]).numpy()
        new_cw = (corr @ start)[:3]
        refined.append(Camera(v.name, v.camera.width, v.camera.height, v.camera.K, new_cw))
        rot_deg, trans = pose_change(v.camera.cam_from_world, new_cw)
        per_view[v.name] = {"rotation_deg": rot_deg, "translation": trans,
                            "translation_rel_depth": trans / res["trans_scale"], "scene_depth": res["trans_scale"],
                            "loss_start": res["loss_start"], "loss_end": res["loss_end"],
                            "best_step": res["best_step"], "steps_run": res["steps_run"],
                            "psnr_start": psnr(before["rgb"].clamp(0.0, 1.0), target), "psnr_end": psnr(rgb, target)}
    write_text_model(out / "sparse" / "0", refined)
    record = {"protocol": PROTOCOL_NAME, "steps": int(steps), "patience": int(patience), "optimizer": "Adam",
              "lr": float(lr),
              "lr_final": testpose_lr(max(steps - 1, 0), steps, lr),
              "loss": "photometric (splat_train.losses.photometric_loss)", "backend": ran, "device": str(device),
              "start": str(cameras), "views": per_view,
              "mean_rotation_deg": float(np.mean([r["rotation_deg"] for r in per_view.values()])) if per_view else None,
              "max_rotation_deg": float(np.max([r["rotation_deg"] for r in per_view.values()])) if per_view else None,
              "mean_translation_rel_depth": (float(np.mean([r["translation_rel_depth"] for r in per_view.values()]))
                                             if per_view else None),
              "wall_time_s": time.perf_counter() - t0}
    write_json(out / "testpose.json", record)
    log.info("test-pose: %d views, %d steps each, in %.1f s", len(views), steps, record["wall_time_s"])
    return record
