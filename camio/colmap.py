"""COLMAP sparse models: the one module that talks to pycolmap.

Reading goes through pycolmap (text or binary, detected from the files present); writing
produces the COLMAP *text* format (cameras.txt, images.txt, points3D.txt) directly, and the
tests read it back with pycolmap. Quaternions in the text files are (w, x, y, z); pycolmap's
``Rotation3d.quat`` is (x, y, z, w) and is converted here and nowhere else.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from camio.atomic import atomic_dir
from camio.cameras import Camera, qvec_to_rotmat, rotmat_to_qvec

__all__ = [
    "MATCHING_THREADS",
    "cpu_matching_options",
    "SparseModel",
    "UnsupportedCameraModelError",
    "PINHOLE_MODELS",
    "find_model_dir",
    "read_model",
    "camera_model_names",
    "write_text_model",
]

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE",
                    "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "FOV", "THIN_PRISM_FISHEYE")


class UnsupportedCameraModelError(ValueError):
    """A camera model that is neither pinhole nor undistorted on request."""


@dataclass
class SparseModel:
    """A posed image set with an optional coloured point cloud.

    Attributes:
        cameras: posed pinhole cameras, sorted by image name.
        points: [N, 3] float64 world points (N may be 0).
        colors: [N, 3] uint8 RGB.
        observations: image name -> (xy [M, 2] float64 pixels, point_idx [M] int64 rows of
            ``points``); empty when unknown.
        camera_models: image name -> (COLMAP model name, params [P] float64) as read,
            before any conversion (for reporting and undistortion).
    """

    cameras: list[Camera]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    observations: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    camera_models: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.cameras = sorted(self.cameras, key=lambda c: c.name)
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        if len(self.colors) == 0 and len(self.points):
            self.colors = np.full((len(self.points), 3), 128, np.uint8)
        self.colors = np.asarray(self.colors, dtype=np.uint8).reshape(-1, 3)
        if len(self.colors) != len(self.points):
            raise ValueError(f"{len(self.points)} points but {len(self.colors)} colours")

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera for image {name!r}")

    def subset(self, names: list[str]) -> "SparseModel":
        """The cameras named (in model order), all points, their observations."""
        wanted = set(names)
        missing = wanted - set(self.names)
        if missing:
            raise KeyError(f"images not in the model: {sorted(missing)}")
        return SparseModel(
            [c for c in self.cameras if c.name in wanted], self.points, self.colors,
            {k: v for k, v in self.observations.items() if k in wanted},
            {k: v for k, v in self.camera_models.items() if k in wanted},
        )


# pycolmap 4.x wheels link a pthreads OpenBLAS statically, and the CPU SIFT matcher calls its
# sgemm (through faiss's exact k-NN) from every matcher thread at once. That OpenBLAS build
# is not safe for concurrent callers: its buffer table races and prints
# "BLAS : Bad memory unallocation!" on stdout, and upstream reports a crash in
# blas_memory_alloc from the same call path (colmap/colmap#3648). Measured with the 3-image
# baseline CLI on 2 cores: 11 of 400 runs as shipped; 30 of 800 with OPENBLAS_NUM_THREADS=1
# or OMP_NUM_THREADS=1 (no help); 0 of 700 with one matcher thread (this code), 0 of 400
# with every stage on one thread. Cost: exhaustive matching of 12 fern images_8 views takes
# 2.1 s instead of 1.6 s. Extraction and mapping keep every core.
MATCHING_THREADS = 1


def cpu_matching_options():
    """pycolmap ``FeatureMatchingOptions`` for CPU matching on :data:`MATCHING_THREADS`
    threads (see the comment above it). Every caller of ``pycolmap.match_*`` uses this."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = MATCHING_THREADS
    matching.use_gpu = False
    return matching


def find_model_dir(path: str | Path) -> Path:
    """The folder that holds cameras.{txt,bin}: ``path`` itself, ``path/sparse/0``,
    ``path/sparse`` or ``path/0``."""
    path = Path(path)
    for cand in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        if any((cand / f"cameras.{ext}").is_file() for ext in ("txt", "bin")):
            return cand
    raise FileNotFoundError(
        f"no COLMAP model (cameras.txt or cameras.bin) in {path} or its sparse/0, sparse, 0 sub-folders"
    )


def _pinhole_K(model: str, params: np.ndarray) -> np.ndarray:
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = params
        fx = fy = f
    elif model == "PINHOLE":
        fx, fy, cx, cy = params
    else:  # pragma: no cover - guarded by the caller
        raise UnsupportedCameraModelError(model)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)


_COUNT_HEADER = re.compile(r"^#\s*Number of (cameras|images|points)\s*:\s*(\d+)")


def _check_text_ends(model_dir: Path) -> None:
    """Every ``*.txt`` of a text model written by COLMAP or :func:`write_text_model` ends
    with a newline; one that does not was cut short (pycolmap would read a line cut
    mid-number as another number, or drop a cut-off last image or point silently)."""
    if (model_dir / "cameras.bin").is_file():
        return  # pycolmap reads the binary model; its reader checks sizes itself
    for fname in ("cameras.txt", "images.txt", "points3D.txt"):
        f = model_dir / fname
        if not f.is_file():
            continue
        with open(f, "rb") as fh:
            fh.seek(0, 2)
            if fh.tell() == 0:
                continue
            fh.seek(-1, 2)
            last = fh.read(1)
        if last != b"\n":
            raise ValueError(f"{f} does not end with a newline: the file is truncated (COLMAP writes a "
                             "newline after every line); copy or export the model again (if you wrote "
                             "it by hand, end it with a newline)")


def _check_text_counts(model_dir: Path, rec) -> None:
    """Where a text file's header states ``# Number of cameras|images|points: N`` (COLMAP's
    writers and :func:`write_text_model` do), the model read must hold N of them: a file cut
    at a line boundary loses whole images or points without any parse error."""
    if (model_dir / "cameras.bin").is_file():
        return
    found = {"cameras": len(rec.cameras), "images": len(rec.images), "points": len(rec.points3D)}
    for fname in ("cameras.txt", "images.txt", "points3D.txt"):
        f = model_dir / fname
        if not f.is_file():
            continue
        with open(f, "rb") as fh:
            head = fh.read(4096).decode("utf-8", errors="replace")
        for line in head.splitlines():
            if not line.startswith("#"):
                break
            m = _COUNT_HEADER.match(line)
            if m and int(m.group(2)) != found[m.group(1)]:
                raise ValueError(f"{f}: the header says {m.group(2)} {m.group(1)} but "
                                 f"{found[m.group(1)]} were read: the file is truncated or damaged; "
                                 "copy or export the model again (if you edited it by hand, correct "
                                 f"the '# Number of {m.group(1)}' line)")


def read_model(path: str | Path, allow_distorted: bool = False) -> SparseModel:
    """Read a COLMAP model (text or binary) with pycolmap.

    Args:
        path: the model folder (or a scene folder holding sparse/0).
        allow_distorted: if False (default) a camera model with distortion raises
            :class:`UnsupportedCameraModelError`; if True its pinhole part (focal lengths,
            principal point) is used and the distortion is ignored -- only for callers that
            undistort the images themselves.

    Returns:
        The model; only registered images with a pose are included.
    """
    import pycolmap

    model_dir = find_model_dir(path)
    _check_text_ends(model_dir)
    rec = pycolmap.Reconstruction()
    try:
        rec.read(str(model_dir))
    except Exception as exc:  # pycolmap raises plain RuntimeError / ValueError / IndexError
        raise ValueError(f"cannot read the COLMAP model in {model_dir} (damaged or inconsistent files?): "
                         f"{exc}") from exc
    _check_text_counts(model_dir, rec)

    cameras: list[Camera] = []
    camera_models: dict[str, tuple[str, np.ndarray]] = {}
    observations: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    point_ids = sorted(rec.points3D.keys())
    row_of = {pid: i for i, pid in enumerate(point_ids)}
    for image_id in sorted(rec.images.keys()):
        img = rec.images[image_id]
        if not img.has_pose:
            continue
        cam = rec.cameras[img.camera_id]
        model = cam.model.name
        params = np.asarray(cam.params, dtype=np.float64)
        camera_models[img.name] = (model, params.copy())
        if model in PINHOLE_MODELS:
            K = _pinhole_K(model, params)
        elif allow_distorted:
            K = np.asarray(cam.calibration_matrix(), dtype=np.float64)
        else:
            raise UnsupportedCameraModelError(
                f"image {img.name!r} uses the distorted camera model {model}; undistort the "
                "scene first (camio.scene.load_scene(..., undistort=True) or "
                "`python -m camio convert --undistort`)"
            )
        pose = img.cam_from_world()
        xyzw = np.asarray(pose.rotation.quat, dtype=np.float64)
        R = qvec_to_rotmat(np.r_[xyzw[3], xyzw[:3]])
        cam_from_world = np.concatenate([R, np.asarray(pose.translation).reshape(3, 1)], axis=1)
        cameras.append(Camera(img.name, cam.width, cam.height, K, cam_from_world))
        xy, idx = [], []
        for p2d in img.points2D:
            if p2d.has_point3D():
                xy.append(np.asarray(p2d.xy, dtype=np.float64))
                idx.append(row_of[p2d.point3D_id])
        observations[img.name] = (np.asarray(xy).reshape(-1, 2), np.asarray(idx, dtype=np.int64))

    points = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
    return SparseModel(cameras, points, colors, observations, camera_models)


def camera_model_names(path: str | Path) -> list[str]:
    """Sorted COLMAP camera model names of every camera in the model at ``path`` (registered
    images or not), for planning; [] when no model is there or it cannot be read."""
    import pycolmap

    try:
        model_dir = find_model_dir(path)
        rec = pycolmap.Reconstruction()
        rec.read(str(model_dir))
    except Exception:  # an unreadable model is the converter's error to report
        return []
    return sorted({c.model.name for c in rec.cameras.values()})


def _nums(*xs: float) -> str:
    """Floats as shortest round-trip decimal strings (lossless for float64)."""
    return " ".join(repr(float(x)) for x in xs)


def _share_intrinsics(cameras: list[Camera]) -> tuple[list[tuple[int, int, np.ndarray]], list[int]]:
    """Group cameras with identical size and K. Returns the unique (w, h, K) and the
    0-based group index of each camera."""
    uniq: list[tuple[int, int, np.ndarray]] = []
    which: list[int] = []
    for cam in cameras:
        for j, (w, h, K) in enumerate(uniq):
            if w == cam.width and h == cam.height and np.array_equal(K, cam.K):
                which.append(j)
                break
        else:
            uniq.append((cam.width, cam.height, cam.K))
            which.append(len(uniq) - 1)
    return uniq, which


def write_text_model(
    path: str | Path,
    cameras: list[Camera],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    observations: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    errors: np.ndarray | None = None,
) -> Path:
    """Write a COLMAP text model (PINHOLE cameras) atomically into ``path``.

    Cameras with identical size and intrinsics share one COLMAP camera. Image ids are
    1..S in the order given; point ids are 1..N in row order.

    Args:
        path: output folder (created; replaced atomically if it exists).
        cameras: posed pinhole cameras.
        points: [N, 3] world points, or None.
        colors: [N, 3] uint8 RGB (grey if None).
        observations: image name -> (xy [M, 2], point_idx [M]) to write as 2D points and
            tracks; optional.
        errors: [N] reprojection errors to store (0 if None).

    Returns:
        The folder written.
    """
    if not cameras:
        raise ValueError("write_text_model: no cameras to write")
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError("write_text_model: duplicate image names")
    for c in cameras:
        if any(ch.isspace() for ch in c.name):
            raise ValueError(f"write_text_model: image name {c.name!r} contains whitespace, "
                             "which the COLMAP text format cannot store")
        if not (np.all(np.isfinite(c.K)) and np.all(np.isfinite(c.cam_from_world))):
            raise ValueError(f"write_text_model: camera {c.name!r} is not finite")
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cols = (np.full((len(pts), 3), 128, np.uint8) if colors is None
            else np.asarray(colors, dtype=np.uint8).reshape(-1, 3))
    errs = np.zeros(len(pts)) if errors is None else np.asarray(errors, dtype=np.float64).reshape(-1)
    if len(cols) != len(pts) or len(errs) != len(pts):
        raise ValueError("write_text_model: points, colors and errors differ in length")
    observations = observations or {}

    uniq, which = _share_intrinsics(cameras)
    cam_lines = ["# Camera list with one line of data per camera:",
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                 f"# Number of cameras: {len(uniq)}"]
    for j, (w, h, K) in enumerate(uniq):
        cam_lines.append(f"{j + 1} PINHOLE {w} {h} " + _nums(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))

    tracks: list[list[tuple[int, int]]] = [[] for _ in range(len(pts))]
    img_lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {len(cameras)}"]
    for i, cam in enumerate(cameras):
        q = rotmat_to_qvec(cam.R)
        t = cam.t
        img_lines.append(
            f"{i + 1} " + _nums(*q, *t) + f" {which[i] + 1} {cam.name}"
        )
        xy, idx = observations.get(cam.name, (np.zeros((0, 2)), np.zeros(0, np.int64)))
        parts = []
        for k, (p, pid) in enumerate(zip(np.asarray(xy).reshape(-1, 2), np.asarray(idx).reshape(-1))):
            if not 0 <= pid < len(pts):
                raise ValueError(f"observation in {cam.name!r} names point row {pid}, out of range")
            parts.append(_nums(p[0], p[1]) + f" {int(pid) + 1}")
            tracks[int(pid)].append((i + 1, k))
        img_lines.append(" ".join(parts))

    pt_lines = ["# 3D point list with one line of data per point:",
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                f"# Number of points: {len(pts)}"]
    for n, (p, c, e) in enumerate(zip(pts, cols, errs)):
        track = " ".join(f"{a} {b}" for a, b in tracks[n])
        pt_lines.append(f"{n + 1} " + _nums(*p) + f" {c[0]} {c[1]} {c[2]} " + _nums(e) + f" {track}".rstrip())

    with atomic_dir(path) as tmp:
        (tmp / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
        (tmp / "images.txt").write_text("\n".join(img_lines) + "\n")
        (tmp / "points3D.txt").write_text("\n".join(pt_lines) + "\n")
    return Path(path)
