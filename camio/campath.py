"""Camera paths for fly-through videos of a scene (numpy, float64).

Every path is a stack of ``cam_from_world`` [F, 4, 4] in the cameras' world frame (OpenCV
camera axes, :mod:`camio`); the caller renders one frame per pose with one intrinsic matrix.

* :func:`interpolate_path` goes through the given cameras in order: rotations by spherical
  linear interpolation (slerp), centres linearly, ``frames_per_segment`` frames per pair.
* :func:`orbit_path` circles the point the cameras look at (:func:`look_centre`) at their mean
  distance from it and mean height along their mean up direction, looking at that point.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from camio.cameras import Camera, look_at, to_homogeneous, qvec_to_rotmat, rotmat_to_qvec

__all__ = ["PATHS", "DEFAULT_FRAMES", "MAX_PATH_FRAMES", "slerp", "interpolate_path", "look_centre", "orbit_path"]

#: the path names ``python -m splat_train render --path`` takes
PATHS = ("interpolate", "orbit")
#: frames of each path unless told otherwise: per pair of cameras (interpolate), per circle (orbit)
DEFAULT_FRAMES = {"interpolate": 30, "orbit": 120}
#: the most frames a path may ask for per camera pair or per circle (a bound on the video's size)
MAX_PATH_FRAMES = 10_000


def slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    Args:
        q0, q1: [4] unit quaternions (w, x, y, z).
        t: [T] fractions in [0, 1].

    Returns:
        [T, 4] unit quaternions; t = 0 gives q0, t = 1 gives q1 or -q1 (the same rotation).
    """
    q0 = np.asarray(q0, np.float64)
    q1 = np.asarray(q1, np.float64)
    t = np.asarray(t, np.float64)[:, None]
    d = float(q0 @ q1)
    if d < 0.0:
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:  # (nearly) the same rotation: linear, renormalised
        q = (1.0 - t) * q0 + t * q1
        return q / np.linalg.norm(q, axis=1, keepdims=True)
    theta = np.arccos(d)
    return (np.sin((1.0 - t) * theta) * q0 + np.sin(t * theta) * q1) / np.sin(theta)


def _pose(R: np.ndarray, centre: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = -R @ centre
    return m


def interpolate_path(cameras: Sequence[Camera], frames_per_segment: int) -> np.ndarray:
    """Poses through ``cameras`` in the given order.

    Between cameras i and i + 1 the frames are at fractions k / n, k = 0..n - 1 (n =
    ``frames_per_segment``): rotation slerped, centre linear. The last camera closes the path.

    Args:
        cameras: M >= 1 cameras (world frame).
        frames_per_segment: n >= 1.

    Returns:
        [(M - 1) * n + 1, 4, 4] cam_from_world; frame i * n is camera i's pose exactly.
    """
    if not cameras:
        raise ValueError("interpolate_path: no cameras")
    if frames_per_segment < 1:
        raise ValueError(f"frames per segment must be >= 1, got {frames_per_segment}")
    n = int(frames_per_segment)
    poses = []
    for a, b in zip(cameras[:-1], cameras[1:]):
        poses.append(to_homogeneous(a.cam_from_world))  # k = 0: the camera itself, exactly
        t = np.arange(1, n) / n
        for tk, q in zip(t, slerp(rotmat_to_qvec(a.R), rotmat_to_qvec(b.R), t)):
            poses.append(_pose(qvec_to_rotmat(q), (1.0 - tk) * a.center + tk * b.center))
    poses.append(to_homogeneous(cameras[-1].cam_from_world))
    return np.stack(poses)


def _up(cameras: Sequence[Camera]) -> np.ndarray:
    """[3] the cameras' mean up direction in the world (image -y), unit length."""
    up = -np.mean([c.R[1] for c in cameras], axis=0)
    norm = np.linalg.norm(up)
    if norm < 1e-9:
        raise ValueError("the cameras' up directions cancel out: no orbit axis; use --path interpolate")
    return up / norm


def look_centre(cameras: Sequence[Camera], max_condition: float = 1e6) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares), in the world frame.

    Args:
        cameras: M >= 2 cameras whose axes are not all parallel.
        max_condition: the largest condition number of the 3 x 3 normal equations accepted.

    Returns:
        [3] the point.

    Raises:
        ValueError: the axes are (nearly) parallel, e.g. a forward-facing capture, or the
            point lies behind the cameras.
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cameras:
        d = c.R[2]  # optical axis (camera +z) in the world
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if len(cameras) < 2 or np.linalg.cond(A) > max_condition:
        raise ValueError("the cameras' optical axes do not meet (parallel or a single camera): no centre to "
                         "orbit; use --path interpolate")
    centre = np.linalg.solve(A, b)
    if np.mean([(centre - c.center) @ c.R[2] for c in cameras]) <= 0:
        raise ValueError("the point the cameras' axes meet lies behind them: no centre to orbit; use --path "
                         "interpolate")
    return centre


def orbit_path(cameras: Sequence[Camera], frames: int, centre: np.ndarray | None = None) -> np.ndarray:
    """A full circle around ``centre`` looking at it.

    The axis is the cameras' mean up direction through ``centre``; the circle lies at the
    cameras' mean height along that axis and their mean distance from it, and starts at the
    first camera's azimuth. Frame k is at azimuth 2 pi k / ``frames`` (the circle is not closed:
    a looping video repeats frame 0 next).

    Args:
        cameras: M >= 2 cameras (world frame).
        frames: F >= 1.
        centre: [3] the point to circle; default :func:`look_centre`.

    Returns:
        [F, 4, 4] cam_from_world; each looks at ``centre`` with the mean up direction up in
        the image.
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    centre = look_centre(cameras) if centre is None else np.asarray(centre, np.float64)
    up = _up(cameras)
    rel = np.stack([c.center for c in cameras]) - centre
    height = rel @ up
    flat = rel - height[:, None] * up
    radius = float(np.mean(np.linalg.norm(flat, axis=1)))
    if radius < 1e-9 * max(1.0, float(np.abs(rel).max())):
        raise ValueError("the cameras lie on the orbit axis: no circle to fly; use --path interpolate")
    e1 = flat[0] / np.linalg.norm(flat[0]) if np.linalg.norm(flat[0]) > 0 else np.cross(up, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    h = float(np.mean(height))
    poses = []
    for a in 2.0 * np.pi * np.arange(frames) / frames:
        eye = centre + h * up + radius * (np.cos(a) * e1 + np.sin(a) * e2)
        poses.append(look_at(eye, centre, up))
    return np.stack(poses)

