"""Train-view pose refinement: a learnable small rigid correction per training camera.

Each camera c has a 6-vector delta_c = (omega, u) (rotation vector in radians, translation in
units of ``trans_scale``), initialised to zero. The refined extrinsics are a left correction in
the camera frame, with v = trans_scale * u:

    cam_from_world'_c = [exp(omega) | v] @ cam_from_world_c,

so delta = 0 is the given pose exactly. ``exp`` is Rodrigues' formula with a Taylor branch
near zero, so the gradient at delta = 0 is finite. The trainer sets ``trans_scale`` to the RMS
distance of the given centres from camera 0 (:func:`camera_spread`), so one learning rate
moves the cameras by the same fraction of their spread on every scene: in the Bridge's units
(median point distance 1) a forward-facing capture such as fern spans a few hundredths, where
a translation rate in scene units that suits an object-centred capture throws the cameras off
(measured: ATE 1.5 -> 30 % of the radius on fern at 1e-3). With ``refine_focal`` each camera also has
a log-focal correction phi_c: fx' = exp(phi_c) fx, fy' = exp(phi_c) fy (principal point kept).

Gauge (the photometric loss does not see it, so it must not drift):

* the first camera (index 0) is not free: its correction is masked to zero;
* the scale is not free: after every pose step :meth:`PoseCorrections.fix_scale_` rescales the
  refined camera centres about camera 0's centre so that their RMS distance from it equals that
  of the given cameras (:func:`scale_gauge_factor`). The Gaussians also pin the scale, but
  only weakly through the view-space gradients; this keeps the refined cameras in the seed's
  units exactly, which the held-out Sim(3) alignment and the benchmarks rely on.

:class:`PoseRefinement` is the training part (:mod:`splat_train.parts.base`): it owns the
corrections and their Adam, gives the trainer the refined camera of each view and steps after
the Gaussians.
"""

from __future__ import annotations

from typing import Any

import torch

from splat_train.parts.base import TrainPart

__all__ = ["so3_exp", "scale_gauge_factor", "camera_spread", "PoseCorrections", "PoseRefinement", "pose_lr_factor"]


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rotation vectors [..., 3] (radians) -> rotation matrices [..., 3, 3] (differentiable,
    finite gradient at 0)."""
    theta2 = (omega * omega).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    small = theta2 < 1e-8
    theta = torch.sqrt(theta2.clamp_min(1e-8))
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-8))
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*omega.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def scale_gauge_factor(centers: torch.Tensor, ref_centers: torch.Tensor) -> torch.Tensor:
    """The scale s that restores the reference spread about camera 0:

        s = sqrt(sum_c ||C_ref_c - C_ref_0||^2 / sum_c ||C_c - C_0||^2),

    so ``C_0 + s (C_c - C_0)`` has the RMS distance from camera 0 of the reference cameras.

    Args:
        centers: [C, 3] camera centres (world frame), camera 0 first.
        ref_centers: [C, 3] reference centres, same order and frame.

    Returns:
        [] scale (1 when the centres coincide).
    """
    num = ((ref_centers - ref_centers[:1]) ** 2).sum()
    den = ((centers - centers[:1]) ** 2).sum()
    # a select, not a Python branch: reading num / den would be a device sync every pose step
    ok = (den >= 1e-24) & (num >= 1e-24)
    return torch.where(ok, torch.sqrt(num / den.clamp_min(1e-24)), torch.ones_like(den))


def camera_spread(cam_from_world: list[torch.Tensor]) -> float:
    """RMS distance of the camera centres from camera 0's (1 when they coincide).

    Args:
        cam_from_world: C [4, 4] (or [3, 4]) world -> camera transforms, camera 0 first.
    """
    m = torch.stack([c[:3] for c in cam_from_world]).double()  # [C, 3, 4]
    centers = -(m[:, :, :3].transpose(1, 2) @ m[:, :, 3:])[..., 0]  # [C, 3] world
    if len(centers) < 2:
        return 1.0
    r = float(((centers - centers[:1]) ** 2).sum(-1)[1:].mean().sqrt())
    return r if r > 1e-12 else 1.0


class PoseCorrections(torch.nn.Module):
    """Per-camera se(3) corrections (and optional log-focal corrections), gauge fixed.

    Args:
        num_cameras: C training cameras.
        refine_focal: also learn one log-focal correction per camera.
        trans_scale: world length of one unit of the translation parameters.

    Attributes:
        delta: [C, 6] parameter (omega, u), zeros at start; row 0 is masked (camera 0 fixed).
        log_focal: [C] parameter (zeros) when ``refine_focal``, else None.
        free: [C, 1] buffer, 0 for the fixed camera, 1 elsewhere.
    """

    def __init__(self, num_cameras: int, device: str | torch.device = "cpu", refine_focal: bool = False,
                 trans_scale: float = 1.0) -> None:
        super().__init__()
        if not trans_scale > 0:
            raise ValueError(f"trans_scale must be > 0, got {trans_scale}")
        self.trans_scale = float(trans_scale)
        if num_cameras < 1:
            raise ValueError(f"pose refinement needs >= 1 camera, got {num_cameras}")
        self.delta = torch.nn.Parameter(torch.zeros(num_cameras, 6, device=device))
        self.log_focal = torch.nn.Parameter(torch.zeros(num_cameras, device=device)) if refine_focal else None
        free = torch.ones(num_cameras, 1, device=device)
        free[0] = 0.0
        self.register_buffer("free", free)

    def correction(self, index: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """[4, 4] left correction [exp(omega) | v] of camera ``index`` (identity for camera 0)."""
        d = (self.delta[index] * self.free[index]).to(dtype)
        top = torch.cat([so3_exp(d[:3]), self.trans_scale * d[3:, None]], 1)
        bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype, device=d.device)
        return torch.cat([top, bottom], 0)

    def forward(self, index: int, cam_from_world: torch.Tensor) -> torch.Tensor:
        """Refined [4, 4] cam_from_world of camera ``index`` from the given [4, 4] one."""
        return self.correction(index, cam_from_world.dtype) @ cam_from_world

    def intrinsics(self, index: int, K: torch.Tensor) -> torch.Tensor:
        """Refined [3, 3] K of camera ``index`` (the given K without focal refinement)."""
        if self.log_focal is None:
            return K
        f = torch.exp(self.log_focal[index] * self.free[index, 0]).to(K.dtype)
        scale = torch.stack([f, f, torch.ones_like(f)])
        return K * scale[None, :]  # K diag(f, f, 1): fx, fy scaled, principal point kept

    @torch.no_grad()
    def fix_scale_(self, cam_from_world: list[torch.Tensor]) -> torch.Tensor:
        """Rescale the refined centres about camera 0 to the given cameras' spread (module
        docstring) by rewriting the translations v; the rotations are unchanged.

        Args:
            cam_from_world: the C given [4, 4] cam_from_world (world frame of the seed).

        Returns:
            [] the scale applied (1 = no drift), on the cameras' device.
        """
        given = torch.stack(cam_from_world).double()  # [C, 4, 4]; float64 for the gauge's sums
        corr = torch.stack([self.correction(i, given.dtype) for i in range(len(given))])
        refined = corr @ given
        R, t = refined[:, :3, :3], refined[:, :3, 3]
        centers = -(R.transpose(1, 2) @ t[..., None])[..., 0]  # [C, 3] world
        ref_centers = -(given[:, :3, :3].transpose(1, 2) @ given[:, :3, 3:])[..., 0]
        s = scale_gauge_factor(centers, ref_centers)
        # C' = C_0 + s (C - C_0), so t' = -R C' = t - (s - 1) R (C - C_0), and v (refined t =
        # exp(omega) t_given + v) moves by the same step. Written as a step, not as t' = -R C'
        # from scratch: the rotations are orthonormal only to float32 precision, and R R^T t
        # would move every camera by ~1e-7 of its translation per call even at s = 1.
        step = -(R @ ((s - 1.0) * (centers - centers[:1]))[..., None])[..., 0]  # [C, 3]
        v = corr[:, :3, 3] + step
        self.delta[:, 3:] = (v * self.free / self.trans_scale).to(self.delta.dtype)
        return s.to(cam_from_world[0].dtype)


def pose_lr_factor(iteration: int, start: int, warmup: int) -> float:
    """Multiplier of the pose (and focal) learning rates at 1-based ``iteration``: 0 before
    ``start``, then a linear ramp (it - start + 1) / warmup up to 1 (1 at once when warmup = 0)."""
    if iteration < start:
        return 0.0
    if warmup <= 0:
        return 1.0
    return min(1.0, (iteration - start + 1) / float(warmup))


class PoseRefinement(TrainPart):
    """Pose (and focal) refinement as a training part.

    From iteration ``refine_from`` on, view c is rendered with the corrected camera
    (:meth:`PoseCorrections.forward`, :meth:`PoseCorrections.intrinsics`); after every
    Gaussian step the corrections take an Adam step at the rates ramped by
    :func:`pose_lr_factor`, and the scale gauge is restored (:meth:`PoseCorrections.fix_scale_`).

    Args:
        given: C [4, 4] cam_from_world of the training views as given (world frame of the seed),
            on the training device, camera 0 first (the fixed one).
        view_names: image name of each view (camera 0's is reported as the fixed camera).
        refine_focal: also learn one log-focal correction per camera.
        lr_pose, lr_focal: Adam rates of the corrections (before the ramp).
        refine_from, warmup: as :func:`pose_lr_factor`.

    Attributes:
        corrections: the :class:`PoseCorrections`; optimizer: their ``torch.optim.Adam``
            (groups "pose" and, with ``refine_focal``, "focal").
    """

    name = "pose"
    moves_cameras = True

    @property
    def moves_intrinsics(self) -> bool:  # type: ignore[override]
        """With focal refinement, the written cameras take the refined K."""
        return self.corrections.log_focal is not None

    def __init__(self, given: list[torch.Tensor], view_names: list[str], refine_focal: bool, lr_pose: float,
                 lr_focal: float, refine_from: int, warmup: int) -> None:
        self.given, self.view_names = list(given), list(view_names)
        self.lr = {"pose": float(lr_pose), "focal": float(lr_focal)}
        self.refine_from, self.warmup = int(refine_from), int(warmup)
        self.corrections = PoseCorrections(len(given), given[0].device, refine_focal=refine_focal,
                                           trans_scale=camera_spread(given))
        groups = [{"params": [self.corrections.delta], "lr": lr_pose, "name": "pose"}]
        if self.corrections.log_focal is not None:
            groups.append({"params": [self.corrections.log_focal], "lr": lr_focal, "name": "focal"})
        self.optimizer = torch.optim.Adam(groups)

    def camera(self, iteration: int, view: int, cam_from_world: torch.Tensor,
               K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The refined [4, 4] cam_from_world and [3, 3] K of ``view`` from ``refine_from`` on
        (differentiable in the corrections), the given ones before."""
        if iteration < self.refine_from:
            return cam_from_world, K
        return self.corrections(view, cam_from_world), self.corrections.intrinsics(view, K)

    def after_step(self, iteration: int, params: dict[str, torch.Tensor]) -> None:
        """Adam step of the corrections at the ramped rates, then the scale gauge (no host read)."""
        f = pose_lr_factor(iteration, self.refine_from, self.warmup)
        for g in self.optimizer.param_groups:
            g["lr"] = f * self.lr[g["name"]]
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.corrections.fix_scale_(self.given)

    def state_dict(self) -> dict[str, Any]:
        """``state``: the corrections ([C, 6] ``delta``, [C] ``log_focal``, [C, 1] ``free``),
        ``optimizer``: their Adam state."""
        return {"state": {k: v.detach().clone() for k, v in self.corrections.state_dict().items()},
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.corrections.load_state_dict(state["state"])
        self.optimizer.load_state_dict(state["optimizer"])

    def summary(self) -> dict[str, Any]:
        """``pose_correction``: the gauge, the largest rotation (radians), translation (world
        units) and log-focal correction."""
        c = self.corrections
        d = c.delta.detach().cpu()
        return {"pose_correction": {
            "fixed_camera": self.view_names[0],
            "gauge": "first camera and the RMS centre distance from it fixed",
            "max_log_focal": None if c.log_focal is None else float(c.log_focal.detach().abs().max()),
            "max_rot_rad": float(d[:, :3].norm(dim=1).max()),
            "max_trans": float(d[:, 3:].norm(dim=1).max()) * c.trans_scale,
            "trans_scale": c.trans_scale}}
