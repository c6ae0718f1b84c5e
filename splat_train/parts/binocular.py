"""Binocular stereo consistency: a self-supervised depth constraint from a shifted copy of a training view.

Binocular3DGS (Han et al., "Binocular-Guided 3D Gaussian Splatting with View Consistency for
Sparse View Synthesis", NeurIPS 2024) trains with no prior from outside the scene: at each
iteration it moves the training camera sideways along its own x axis by a random baseline,
renders that shifted view, warps the shifted render back into the training view with the
disparity of the training render's own depth, ``d = fx * shift / z``, and compares the warp
with the training image (an L1 over the pixels the warp reaches) plus an edge-aware
smoothness of the disparity. The warp matches the training image only where the rendered
depth is the depth of the surface the colour comes from, so the term pulls colour onto
surfaces at the right depth, the parallax the training views alone do not pin down.

Its release (hanl2010/Binocular3DGS ``train.py``) draws the shift uniformly in [-0.4, 0.4]
scene units and turns the term on after 20,000 of 30,000 iterations, with weight 1 on the L1
and 0.05 on the smoothness. Here the shift is a fraction of the view's median rendered depth
(``binocular_shift``), so that it follows the scene's scale: 0.4 units is 1.0-1.4 % of the
median depth of LLFF fern, horns and trex's points in their COLMAP frames (0.6 % on flower).

Conventions: images [H, W, 3] RGB, depths [H, W] camera z (OpenCV camera: x right, y down,
z forward), cameras [4, 4] cam_from_world, intrinsics [3, 3] in pixels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from splat_train.rng import uniform
from splat_train.parts.base import TrainPart, ViewRenderer

__all__ = ["SMOOTH_WEIGHT", "EDGE_SCALE", "shifted_camera", "warp_from_shifted", "disparity_smoothness",
           "binocular_consistency_loss", "BinocularConsistency"]

# Binocular3DGS's weight of the disparity smoothness beside the warp's L1 (weight 1)
SMOOTH_WEIGHT = 0.05
# its edge scale: the smoothness weighs a disparity step by exp(-EDGE_SCALE |image step|)
EDGE_SCALE = 0.33


def shifted_camera(cam_from_world: Tensor, shift: Tensor | float) -> Tensor:
    """The camera moved by ``shift`` along its own x axis (the right-hand camera of a stereo pair
    for ``shift`` > 0).

    Args:
        cam_from_world: [4, 4] world -> OpenCV camera.
        shift: [] or float, in world units.

    Returns:
        [4, 4] cam_from_world of the shifted camera: same rotation, its centre at
        ``C + shift * R^T e_x`` (a point's camera x decreases by ``shift``).
    """
    out = cam_from_world.clone()
    out[0, 3] = cam_from_world[0, 3] - shift
    return out


def warp_from_shifted(shifted_rgb: Tensor, depth: Tensor, fx: Tensor | float, shift: Tensor | float
                      ) -> tuple[Tensor, Tensor, Tensor]:
    """Warp the shifted camera's render into the training view with the training view's depth.

    A training pixel (u, v) at depth z is seen by the camera shifted by ``shift`` along x at
    (u - fx shift / z, v): the warp samples the shifted render there, bilinearly along the row.

    Args:
        shifted_rgb: [H, W, C] render of :func:`shifted_camera` (differentiable).
        depth: [H, W] camera z of the training view's render (> 0 where it renders anything;
            a depth <= 0 sends the pixel out of the image, so it is not valid).
        fx: horizontal focal length in pixels; shift: as :func:`shifted_camera`.

    Returns:
        (warped [H, W, C], valid [H, W] float 0/1: the sample lies inside the shifted image,
        disparity [H, W] fx shift / z in pixels, 0 where not valid).
    """
    h, w = depth.shape
    z = depth.clamp_min(1e-12)
    disparity = fx * shift / z
    cols = torch.arange(w, dtype=depth.dtype, device=depth.device).expand(h, w)
    rows = torch.arange(h, dtype=depth.dtype, device=depth.device)[:, None].expand(h, w)
    u = cols - disparity
    valid = ((u >= 0) & (u <= w - 1) & (depth > 0)).to(depth.dtype)
    # grid_sample with align_corners=True: -1 and 1 are the centres of the first and last pixel
    gx = torch.where(valid > 0, u, cols) * (2.0 / max(w - 1, 1)) - 1.0
    gy = rows * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], dim=-1)[None].to(shifted_rgb.dtype)
    warped = F.grid_sample(shifted_rgb.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border",
                           align_corners=True)[0].permute(1, 2, 0)
    return warped * valid[..., None], valid, disparity * valid


def disparity_smoothness(disparity: Tensor, image: Tensor, valid: Tensor | None = None) -> Tensor:
    """Edge-aware first-order smoothness of a disparity map (Binocular3DGS's, after Monodepth).

    Central differences (half the step between the two neighbours) of the disparity, each
    weighed by ``exp(-EDGE_SCALE |sum over channels of the image's central difference|)``, so that
    disparity may jump where the image has an edge. With ``valid``, a difference counts only
    where both neighbours are valid (Binocular3DGS smooths the masked disparity, whose step to 0
    at the edge of the warp's reach pulls the depth there).

    Args:
        disparity: [H, W] in pixels.
        image: [H, W, 3] the training image.
        valid: [H, W] 0/1, or None (every pixel).

    Returns:
        [] mean |weighted x step| + mean |weighted y step| over the interior pixels.
    """
    dx_d = 0.5 * (disparity[1:-1, 2:] - disparity[1:-1, :-2])
    dy_d = 0.5 * (disparity[2:, 1:-1] - disparity[:-2, 1:-1])
    wx = torch.exp(-EDGE_SCALE * (0.5 * (image[1:-1, 2:] - image[1:-1, :-2]).sum(-1)).abs())
    wy = torch.exp(-EDGE_SCALE * (0.5 * (image[2:, 1:-1] - image[:-2, 1:-1]).sum(-1)).abs())
    if valid is not None:
        wx = wx * valid[1:-1, 2:] * valid[1:-1, :-2]
        wy = wy * valid[2:, 1:-1] * valid[:-2, 1:-1]
    return (wx * dx_d).abs().mean() + (wy * dy_d).abs().mean()


def binocular_consistency_loss(target: Tensor, depth: Tensor, shifted_rgb: Tensor, fx: Tensor | float,
                               shift: Tensor | float) -> Tensor:
    """Binocular3DGS's consistency loss of one training view and its shifted copy.

    ``sum(valid |warped - target|) / (3 H W) + SMOOTH_WEIGHT * smoothness(disparity, valid)``: both
    are averaged over every pixel, so pixels the warp does not reach add nothing.

    Args:
        target: [H, W, 3] the training image.
        depth: [H, W] camera z of the training render (differentiable).
        shifted_rgb: [H, W, 3] render of the camera shifted by ``shift`` (differentiable).
        fx: focal length in pixels; shift: world units.

    Returns:
        [] the loss (unweighted).
    """
    warped, valid, disparity = warp_from_shifted(shifted_rgb, depth, fx, shift)
    l1 = (valid[..., None] * (warped - target).abs()).mean()
    return l1 + SMOOTH_WEIGHT * disparity_smoothness(disparity, target, valid)


class BinocularConsistency(TrainPart):
    """The binocular consistency term as a training part: from ``start`` on, each training
    render's view is rendered again from a camera shifted sideways by
    ``U(-1, 1) x max_shift x`` the render's median depth (over pixels of alpha > 0.5), and
    ``weight x`` :func:`binocular_consistency_loss` is added. The shifted render has no
    dropout (as in Binocular3DGS, which has none) and reads no densification statistics.

    Args:
        weight: the term's weight (Binocular3DGS's 1; > 0).
        max_shift: the largest shift as a fraction of the view's median depth.
        start: the first iteration with the term is ``start + 1``.
        iterations: the run's length (the term acts in ``iterations - start`` of them).
        targets: [H, W, 3] training image of each view, on the training device.
        generator: the trainer's CPU generator (the shifts).
        renderer: the trainer (:class:`splat_train.parts.base.ViewRenderer`).
    """

    name = "binocular"
    needs_depth = True

    def __init__(self, weight: float, max_shift: float, start: int, iterations: int, targets: list[Tensor],
                 generator: torch.Generator, renderer: ViewRenderer) -> None:
        self.weight, self.max_shift = float(weight), float(max_shift)
        self.start, self.iterations = int(start), int(iterations)
        self.targets, self.gen, self.renderer = targets, generator, renderer

    def loss(self, iteration: int, view: int, render: dict[str, Tensor], params: dict[str, Tensor]) -> Tensor | None:
        """The weighted term of training view ``view`` (``render``: its ``depth`` [H, W] and
        ``alpha`` [H, W]), or None before ``start``."""
        if iteration <= self.start:
            return None
        depth, alpha = render["depth"], render["alpha"]
        # nothing read back to the host (on a GPU a read waits for the device): a view that
        # renders no pixel of alpha > 0.5 has median 0, so no shift, the warp is the identity
        # and the term is the L1 of the view's own render without dropout
        surface = alpha.detach() > 0.5
        median = torch.nan_to_num(torch.nanmedian(torch.where(surface, depth.detach(), torch.nan)), nan=0.0)
        u = uniform(1, self.gen, depth.device, depth.dtype)[0]
        shift = (2.0 * u - 1.0) * self.max_shift * median
        cam_from_world, K = self.renderer.view_camera(view)
        h, w = depth.shape
        shifted = self.renderer.render_rgb(shifted_camera(cam_from_world.detach(), shift), K.detach(), w, h)
        return self.weight * binocular_consistency_loss(self.targets[view], depth, shifted, K[0, 0].detach(), shift)

    def summary(self) -> dict:
        """``binocular``: how many iterations of the run add the term, its weight and largest shift."""
        return {"binocular": {"terms": max(0, self.iterations - self.start), "weight": self.weight,
                              "max_shift": self.max_shift, "from_iteration": self.start + 1}}
