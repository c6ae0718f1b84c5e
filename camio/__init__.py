"""camio: camera maths, scenes and file formats shared by every stage.

One job: cameras, scenes and the files they live in. Beside it on the ground floor:
:mod:`runtime` (flags, logging, memory, C++ builds) and :mod:`imgmetrics` (SSIM, LPIPS).

Conventions (stated once, converted at every boundary):

* Extrinsics are ``cam_from_world`` ([3,4] or [4,4], float64): ``x_cam = R @ x_world + t``.
* Camera axes are OpenCV's: x right, y down, z forward (looking along +z).
* Pixel coordinates are continuous with the COLMAP convention: the centre of the top-left
  pixel is (0.5, 0.5); pixel (row i, column j) has its centre at (j + 0.5, i + 0.5). An
  intrinsic matrix ``K`` maps camera coordinates to these pixel coordinates, so scaling an
  image by (sx, sy) scales fx, cx by sx and fy, cy by sy exactly.
* Quaternions are (w, x, y, z) everywhere in this project (COLMAP text, 3DGS PLY ``rot_*``).
  pycolmap's ``Rotation3d.quat`` is (x, y, z, w); only :mod:`camio.colmap` touches it.
* Images are float32 RGB in [0, 1], shape [H, W, 3], unless a function says otherwise.
"""

from runtime.stops import early_if_main as _early

_early()  # first: a stop while `python -m` loads the command is one line, exit 128 + the signal

from camio.cameras import (
    Camera,
    camera_center,
    invert_cam_from_world,
    qvec_to_rotmat,
    rotmat_to_qvec,
    to_homogeneous,
)

__all__ = [
    "Camera",
    "camera_center",
    "invert_cam_from_world",
    "qvec_to_rotmat",
    "rotmat_to_qvec",
    "to_homogeneous",
]
