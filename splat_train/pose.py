"""Train-view pose refinement: a learnable small rigid correction per training camera.

Each camera c has a 6-vector delta_c = (omega, v) (rotation vector in radians, translation in
scene units), initialised to zero. The refined extrinsics are a left correction in the camera
frame:

    cam_from_world'_c = [exp(omega) | v] @ cam_from_world_c,

so delta = 0 is the given pose exactly. ``exp`` is Rodrigues' formula with a Taylor branch
near zero, so the gradient at delta = 0 is finite.
"""

from __future__ import annotations

import torch

__all__ = ["so3_exp", "PoseCorrections"]


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


class PoseCorrections(torch.nn.Module):
    """Per-camera se(3) corrections.

    Args:
        num_cameras: C training cameras.

    Attributes:
        delta: [C, 6] parameter (omega, v), zeros at start.
    """

    def __init__(self, num_cameras: int, device: str | torch.device = "cpu") -> None:
        super().__init__()
        self.delta = torch.nn.Parameter(torch.zeros(num_cameras, 6, device=device))

    def forward(self, index: int, cam_from_world: torch.Tensor) -> torch.Tensor:
        """Refined [4, 4] cam_from_world of camera ``index`` from the given [4, 4] one."""
        d = self.delta[index]
        corr = torch.eye(4, dtype=cam_from_world.dtype, device=cam_from_world.device)
        corr = torch.cat([torch.cat([so3_exp(d[:3]).to(cam_from_world.dtype),
                                     d[3:, None].to(cam_from_world.dtype)], 1), corr[3:]], 0)
        return corr @ cam_from_world
