"""Rendering trained Gaussians into camera sets: PNG files and PSNR against images.

Used by the trainer at the end of a run and by ``python -m splat_train render`` (the
evaluation stage renders the held-out cameras with it). Output names: the image name with
its suffix replaced by ``.png``, e.g. ``IMG_0001.JPG -> IMG_0001.png``; image names are plain
file names (every reader checks them, :mod:`runtime.names`) and no two share a stem
(:func:`splat_train.data.load_views`), so every render is its own file inside ``out_dir``.
``python -m splat_train render --alpha`` also writes each render's accumulated opacity as
``out_dir/alpha/<stem>.png`` (16-bit gray, :mod:`camio.alpha`), which the image metrics read to
score the pixels the model covers (the workflow's held-out renders ask for it).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from camio import Camera
from camio.alpha import alpha_path, write_alpha
from camio.images import write_image
from camio.ply import read_gaussian_ply
from runtime.checks import RGB
from runtime.logs import progress
from splat_train.data import View, load_views, read_name_list
from splat_train.gaussians import activated, params_from_cloud
from splat_train.losses import psnr
from splat_train.render.rasterize import rasterize
from splat_train.recipes import BACKGROUND_BLACK

__all__ = ["render_params", "render_views", "render_model", "render_name", "model_background", "background_note", "parse_background"]

log = logging.getLogger(__name__)


def model_background(model: str | Path) -> tuple[tuple[float, float, float], str]:
    """The colour a trained model was trained against, to render it against: the config
    ``background`` of the ``train.json`` beside ``model`` (RGB in [0, 1]; the trainer keeps the
    resolved colour there, a recipe's "mean" included), and where it came from (that file's path).
    Without a train.json, or with one whose config has no colour (a model from another trainer):
    black (:data:`splat_train.recipes.BACKGROUND_BLACK`) and "default".

    Raises:
        ValueError: one line naming the train.json: it cannot be read, is not a JSON object, or
            its colour is not three finite numbers in [0, 1] (a NaN would zero a channel).
    """
    tj = Path(model).with_name("train.json")
    if not tj.exists():
        return BACKGROUND_BLACK, "default"
    try:
        data = json.loads(tj.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{tj}: cannot be read ({exc.strerror if isinstance(exc, OSError) else exc}); "
                         "fix or remove it, or pass --background R,G,B") from None
    except ValueError as exc:
        raise ValueError(f"{tj}: not JSON ({exc}); fix or remove it, or pass --background R,G,B") from None
    config = data.get("config", {}) if isinstance(data, dict) else None
    if not isinstance(config, dict):
        raise ValueError(f"{tj}: not a training summary (a JSON object whose config is an object); fix or remove "
                         "it, or pass --background R,G,B")
    bg = config.get("background")
    if bg is None:
        return BACKGROUND_BLACK, "default"
    try:
        RGB.check(bg, "config background")
    except ValueError as exc:
        raise ValueError(f"{tj}: {exc}; fix or remove it, or pass --background R,G,B") from None
    return (float(bg[0]), float(bg[1]), float(bg[2])), str(tj)


def background_note(rgb: tuple[float, float, float], source: str) -> str:
    """One line on the colour a model is drawn on and where it came from (``source`` as
    :func:`model_background` or a ``--background`` flag gives it), the same in every command's log."""
    where = "black: no train.json with one beside the model" if source == "default" else source
    return f"background {','.join(f'{x:g}' for x in rgb)} ({where})"


def parse_background(text: str) -> tuple[float, float, float]:
    """A ``--background`` value, ``R,G,B`` in [0, 1] (``1,1,1`` is white), as three floats; the
    same for every command that draws a model (``render``, ``view``). ValueError naming what is
    wrong otherwise."""
    try:
        rgb = tuple(float(x) for x in text.split(","))
    except ValueError:
        rgb = ()
    if not RGB.ok(rgb):
        raise ValueError(f"--background must be three numbers in [0, 1] like 0,0,0, got {text!r}")
    return rgb


def render_name(image_name: str) -> str:
    """Relative output path of a render: ``name`` with suffix ``.png``."""
    return str(Path(image_name).with_suffix(".png"))


def camera_tensors(cam: Camera, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """(cam_from_world [4, 4], K [3, 3]) float32 tensors of a camera."""
    m = np.eye(4)
    m[:3] = cam.cam_from_world
    return (torch.as_tensor(m, dtype=torch.float32, device=device),
            torch.as_tensor(cam.K, dtype=torch.float32, device=device))


def render_params(params: dict[str, torch.Tensor], sh_degree: int, cam_from_world: torch.Tensor,
                  K: torch.Tensor, width: int, height: int, background: torch.Tensor,
                  backend: str = "auto",
                  opacity_fn: Callable[[torch.Tensor], torch.Tensor] | None = None, depth: bool = True,
                  stats: bool = True) -> dict:
    """Rasterize the trainable Gaussians (:mod:`splat_train.gaussians`) into one camera.

    Args:
        cam_from_world: [4, 4] world -> OpenCV camera; K: [3, 3] pixels.
        background: [3] RGB.
        backend: :func:`splat_train.rasterize` backend.
        opacity_fn: maps the [N] opacities (after the sigmoid) before rasterizing; training's
            Gaussian dropout (:mod:`splat_train.parts.dropout`). None for every scored render.
        depth: whether the render's depth is needed (:func:`splat_train.rasterize`'s ``depth``).
        stats: whether the densification statistics are read (:func:`splat_train.rasterize`'s
            ``stats``).

    Returns:
        The :func:`splat_train.rasterize` dict (``rgb`` [H, W, 3], ``means2d`` [N, 2], ...).
    """
    scales, opac, quats = activated(params)
    if opacity_fn is not None:
        opac = opacity_fn(opac)
    # SH as the (sh_dc, sh_rest) pair: the fused CPU projection reads both parameters in place
    # and writes their gradients directly (no [N, 16, 3] concatenation and slice-gradient copy
    # per iteration); other backends concatenate
    return rasterize(params["means"], quats, scales, opac, (params["sh_dc"], params["sh_rest"]),
                     cam_from_world, K, width, height, background=background, sh_degree=sh_degree,
                     backend=backend, depth=depth, stats=stats)


@torch.no_grad()
def render_views(params: dict[str, torch.Tensor], sh_degree: int, views: list[View],
                 background: torch.Tensor, out_dir: str | Path | None = None,
                 cam_override: list[torch.Tensor] | None = None, desc: str = "render",
                 K_override: list[torch.Tensor] | None = None, backend: str = "auto",
                 on_render: Callable[[str, torch.Tensor, torch.Tensor, torch.Tensor], None] | None = None,
                 alpha: bool = False) -> dict[str, float]:
    """Render every view; write PNGs into ``out_dir`` (if given); PSNR where a view has an image.

    Args:
        on_render: called as ``on_render(name, rgb, target, alpha)`` for every view with an
            image (``rgb`` the render clamped to [0, 1] and ``target`` the image, both [H, W, 3],
            and ``alpha`` [H, W] the render's accumulated opacity, on the model's device), e.g.
            :class:`splat_train.training.heldout.HeldoutScorer`.
        cam_override: optional [4, 4] cam_from_world per view (refined poses).
        K_override: optional [3, 3] intrinsics per view in its image pixels (refined focal).
        backend: :func:`splat_train.rasterize` backend.
        alpha: also write each render's accumulated opacity [H, W] to ``out_dir/alpha/<stem>.png``
            (:func:`camio.alpha.write_alpha`).

    Returns:
        image name -> PSNR in dB (only views with an image).
    """
    dev = params["means"].device
    scores: dict[str, float] = {}
    for i, v in enumerate(progress(views, desc=desc)):
        cw, K = camera_tensors(v.camera, dev)
        if cam_override is not None:
            cw = cam_override[i].to(dev)
        if K_override is not None:
            K = K_override[i].to(dev)
        out = render_params(params, sh_degree, cw, K, v.camera.width, v.camera.height, background, backend)
        rgb = out["rgb"].clamp(0.0, 1.0)
        if v.image is not None:
            target = torch.as_tensor(v.image, device=dev)
            scores[v.name] = psnr(rgb, target)
            if on_render is not None:
                on_render(v.name, rgb, target, out["alpha"])
        if out_dir is not None:
            write_image(Path(out_dir) / render_name(v.name), rgb.cpu().numpy())
            if alpha:
                write_alpha(alpha_path(out_dir, render_name(v.name)), out["alpha"].cpu().numpy())
    return scores


def render_model(model: str | Path, cameras: str | Path, out_dir: str | Path,
                 images: str | Path | None = None, width: int | None = None, height: int | None = None,
                 names: str | Path | None = None, background: tuple[float, float, float] | None = None,
                 device: str = "cpu", alpha: bool = False) -> dict[str, float]:
    """Render a trained ``model.ply`` into every camera of a COLMAP folder and write PNGs; with
    ``alpha``, each render's accumulated opacity in ``out_dir/alpha/`` too (:mod:`camio.alpha`).

    Image sizes: the camera sizes; or those of the same-named files in ``images`` (K rescaled;
    the PSNR against them is returned); or ``width`` x ``height`` for every camera.
    ``background``: RGB in [0, 1] behind the Gaussians; None: the one the model was trained
    against (:func:`model_background`).

    Returns:
        image name -> PSNR (empty without ``images``).
    """
    t0 = time.perf_counter()
    if background is None:
        background, source = model_background(model)
        log.info("%s", background_note(background, source))
    name_list = read_name_list(names) if names is not None else None
    # an RGBA image is scored on the colour the render is drawn on
    views = load_views(cameras, images, name_list, background=tuple(background), read_pixels=images is not None)
    if (width is None) != (height is None):
        raise ValueError("give both --width and --height, or neither")
    if width is not None:
        views = [View(v.camera.scaled(int(width), int(height)), None) for v in views]
    cloud = read_gaussian_ply(model)
    params = params_from_cloud(cloud, sh_degree=cloud.sh_degree, device=device)
    bg = torch.tensor(background, dtype=torch.float32, device=device)
    scores = render_views(params, cloud.sh_degree, views, bg, out_dir, alpha=alpha)
    log.info("rendered %d views of %s (%d Gaussians) into %s in %.1f s%s", len(views), model,
             len(cloud), out_dir, time.perf_counter() - t0,
             f", mean PSNR {np.mean(list(scores.values())):.2f} dB" if scores else "")
    return scores
