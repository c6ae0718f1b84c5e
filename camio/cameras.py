"""Pinhole cameras and rigid-transform helpers (numpy, float64).

Convention: see :mod:`camio`. ``cam_from_world`` maps world points into the OpenCV camera
frame; ``K`` maps camera coordinates to continuous pixel coordinates whose top-left pixel
centre is (0.5, 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Camera",
    "qvec_to_rotmat",
    "rotmat_to_qvec",
    "to_homogeneous",
    "invert_cam_from_world",
    "camera_center",
    "project_points",
    "scale_intrinsics",
    "opengl_to_opencv_c2w",
    "look_at",
]


def qvec_to_rotmat(qvec: np.ndarray) -> np.ndarray:
    """Rotation matrix from a (w, x, y, z) quaternion.

    Args:
        qvec: [..., 4] quaternion (w, x, y, z); need not be unit length (it is normalised).

    Returns:
        [..., 3, 3] rotation matrix.

    Raises:
        ValueError: on a wrong shape or a zero / non-finite quaternion.
    """
    q = np.asarray(qvec, dtype=np.float64)
    if q.shape[-1] != 4:
        raise ValueError(f"qvec must have shape [..., 4], got {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError("qvec must be finite and non-zero")
    w, x, y, z = np.moveaxis(q / norm, -1, 0)
    r = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return r.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_qvec(rotmat: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternion with w >= 0 from a rotation matrix.

    Uses the symmetric-eigenvector method, which is stable for every rotation angle.

    Args:
        rotmat: [3, 3] rotation matrix.

    Returns:
        [4] quaternion (w, x, y, z), w >= 0.
    """
    r = np.asarray(rotmat, dtype=np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotmat must have shape [3, 3], got {r.shape}")
    rxx, ryx, rzx, rxy, ryy, rzy, rxz, ryz, rzz = r.flat
    k = np.array(
        [
            [rxx - ryy - rzz, 0, 0, 0],
            [ryx + rxy, ryy - rxx - rzz, 0, 0],
            [rzx + rxz, rzy + ryz, rzz - rxx - ryy, 0],
            [ryz - rzy, rzx - rxz, rxy - ryx, rxx + ryy + rzz],
        ]
    ) / 3.0
    vals, vecs = np.linalg.eigh(k)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    if q[0] < 0:
        q = -q
    return q / np.linalg.norm(q)


def to_homogeneous(cam_from_world: np.ndarray) -> np.ndarray:
    """[3,4] or [4,4] (batched [..., 3|4, 4]) -> [..., 4, 4] homogeneous transform."""
    m = np.asarray(cam_from_world, dtype=np.float64)
    if m.shape[-2:] == (4, 4):
        return m.copy()
    if m.shape[-2:] != (3, 4):
        raise ValueError(f"expected [..., 3, 4] or [..., 4, 4], got {m.shape}")
    out = np.zeros(m.shape[:-2] + (4, 4))
    out[..., :3, :] = m
    out[..., 3, 3] = 1.0
    return out


def invert_cam_from_world(cam_from_world: np.ndarray) -> np.ndarray:
    """Invert a rigid transform: cam_from_world [..., 3|4, 4] -> world_from_cam [..., 4, 4]."""
    m = to_homogeneous(cam_from_world)
    r = m[..., :3, :3]
    t = m[..., :3, 3]
    out = np.zeros_like(m)
    rt = np.swapaxes(r, -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t)
    out[..., 3, 3] = 1.0
    return out


def camera_center(cam_from_world: np.ndarray) -> np.ndarray:
    """Camera centre in world coordinates, C = -R^T t.  [..., 3|4, 4] -> [..., 3]."""
    m = np.asarray(cam_from_world, dtype=np.float64)
    r = m[..., :3, :3]
    t = m[..., :3, 3]
    return -np.einsum("...ji,...j->...i", r, t)


def project_points(
    points_world: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into pixels.

    Args:
        points_world: [N, 3] world points.
        K: [3, 3] intrinsics (COLMAP pixel convention).
        cam_from_world: [3|4, 4] extrinsics.

    Returns:
        uv: [N, 2] pixel coordinates (column, row); NaN where depth <= 0.
        depth: [N] z in the camera frame.
    """
    p = np.asarray(points_world, dtype=np.float64)
    m = to_homogeneous(cam_from_world)
    pc = p @ m[:3, :3].T + m[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = pc @ np.asarray(K, dtype=np.float64).T
        uv = uvw[:, :2] / uvw[:, 2:3]
    uv[z <= 0] = np.nan
    return uv, z


def scale_intrinsics(K: np.ndarray, sx: float, sy: float | None = None) -> np.ndarray:
    """Intrinsics of an image resized by (sx, sy) (new_size = old_size * s), [3,3] -> [3,3].

    Exact in the COLMAP pixel convention: continuous coordinates scale linearly.
    """
    sy = sx if sy is None else sy
    out = np.asarray(K, dtype=np.float64).copy()
    out[0, :] *= sx
    out[1, :] *= sy
    return out


_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def opengl_to_opencv_c2w(c2w_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world in OpenGL axes (x right, y up, z back) -> cam_from_world [..., 4, 4]
    in OpenCV axes."""
    m = to_homogeneous(c2w_gl)
    m[..., :3, :3] = m[..., :3, :3] @ _GL_TO_CV
    return invert_cam_from_world(m)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """cam_from_world [4, 4] (OpenCV axes) of a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear up in the image (image -y).
    """
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: view direction is parallel to up")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    r = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = -r @ eye
    return out


@dataclass
class Camera:
    """One posed pinhole image.

    Attributes:
        name: image file name (relative to the scene's image folder), the key that matches
            cameras across models.
        width, height: image size in pixels.
        K: [3, 3] float64 intrinsics (COLMAP pixel convention).
        cam_from_world: [3, 4] float64 extrinsics (OpenCV axes).
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    cam_from_world: np.ndarray = field(default_factory=lambda: np.eye(4)[:3])

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.cam_from_world = to_homogeneous(self.cam_from_world)[:3]
        self.width = int(self.width)
        self.height = int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: size must be positive, got {self.width}x{self.height}")

    @property
    def R(self) -> np.ndarray:
        return self.cam_from_world[:, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_world[:, 3]

    @property
    def center(self) -> np.ndarray:
        return camera_center(self.cam_from_world)

    @property
    def qvec(self) -> np.ndarray:
        """(w, x, y, z) rotation of cam_from_world."""
        return rotmat_to_qvec(self.R)

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera for the image resized to (width, height)."""
        K = scale_intrinsics(self.K, width / self.width, height / self.height)
        return Camera(self.name, width, height, K, self.cam_from_world.copy())
