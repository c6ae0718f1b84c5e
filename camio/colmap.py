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

from runtime.atomic import atomic_dir
from camio.cameras import Camera, qvec_to_rotmat, rotmat_to_qvec
from camio.limits import check_image_size
from runtime.names import check_name

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
# with every stage on one thread. Cost: matching runs on one core (about a third slower on
# 12 small views). Extraction and mapping keep every core.
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


# Number of leading focal-length parameters of each COLMAP camera model (f, or fx fy).
_FOCALS = {"SIMPLE_PINHOLE": 1, "SIMPLE_RADIAL": 1, "RADIAL": 1, "SIMPLE_RADIAL_FISHEYE": 1, "RADIAL_FISHEYE": 1,
           "PINHOLE": 2, "OPENCV": 2, "FULL_OPENCV": 2, "OPENCV_FISHEYE": 2, "FOV": 2, "THIN_PRISM_FISHEYE": 2}


PRINCIPAL_POINT_SLACK = 1.0
"""A principal point may lie up to this many image sizes outside the image (cx in
[-s w, (1 + s) w], cy likewise) before the camera is refused; outside the image but within
that bound it is read with a warning. A principal point outside the image happens only for
crops of a larger image; one further out is a damaged or mis-scaled model (training on it
gives a few dB)."""

DISTORTION_FOV_FACTOR = 10.0
"""Distortion may change the radius of the image's farthest corner (in normalised
coordinates) by at most this factor; OPENCV k1 = 1e12 shrinks the undistorted view to a
point (every undistorted image black) and is refused."""

# parameter layout of the distorted models: (number of focal lengths, radial terms' slice,
# kind: "poly" r(1 + k1 r^2 + k2 r^4 + ...), "rational" (FULL_OPENCV), "fisheye" theta-based)
_DISTORTION = {"SIMPLE_RADIAL": (slice(3, 4), "poly"), "RADIAL": (slice(3, 5), "poly"),
               "OPENCV": (slice(4, 6), "poly"), "FULL_OPENCV": (slice(4, 12), "rational"),
               "OPENCV_FISHEYE": (slice(4, 8), "fisheye"), "SIMPLE_RADIAL_FISHEYE": (slice(3, 4), "fisheye"),
               "RADIAL_FISHEYE": (slice(3, 5), "fisheye")}


def _radial_map(kind: str, k: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Distorted normalised radius of the undistorted radius (or angle, fisheye) ``x`` [N]."""
    if kind == "rational":  # k1 k2 p1 p2 k3 k4 k5 k6: (1 + k1 r2 + k2 r4 + k3 r6) / (1 + k4 r2 + k5 r4 + k6 r6)
        r2 = x * x
        num = 1 + k[0] * r2 + k[1] * r2**2 + k[4] * r2**3
        den = 1 + k[5] * r2 + k[6] * r2**2 + k[7] * r2**3
        with np.errstate(all="ignore"):
            return x * num / den
    r2 = x * x
    poly = 1 + sum(kk * r2 ** (j + 1) for j, kk in enumerate(k))
    return x * poly


def camera_problem(model: str, width: int, height: int, params) -> tuple[str | None, str | None]:
    """(refusal, warning) for one camera's values, each a sentence or None.

    Refused: a principal point more than :data:`PRINCIPAL_POINT_SLACK` image sizes outside
    the image; distortion under which undistortion is not defined over the image (the
    distorted radius not strictly increasing out to the farthest corner, or changing that
    corner's radius by more than :data:`DISTORTION_FOV_FACTOR`). Warned: a principal point
    outside the image but within that bound.
    """
    params = np.asarray(params, dtype=np.float64)
    nf = _FOCALS.get(model, 0)
    if not nf or len(params) < nf + 2 or not np.all(np.isfinite(params)):
        return None, None
    cx, cy = params[nf], params[nf + 1]
    s = PRINCIPAL_POINT_SLACK
    if not (-s * width <= cx <= (1 + s) * width and -s * height <= cy <= (1 + s) * height):
        return (f"has the principal point ({cx:g}, {cy:g}), more than {s:g} image size outside its {width}x{height} "
                "image (a damaged or mis-scaled model)"), None
    warning = None
    if not (0 <= cx <= width and 0 <= cy <= height):
        warning = f"has the principal point ({cx:g}, {cy:g}) outside its {width}x{height} image"
    spec = _DISTORTION.get(model)
    f = float(np.min(params[:nf])) if nf else 0.0
    if spec is None or not f > 0:
        return None, warning
    sl, kind = spec
    k = params[sl] if kind != "rational" else params[4:12]
    if not np.any(k):
        return None, warning
    corner = max(np.hypot(u - cx, v - cy) for u in (0, width) for v in (0, height)) / f
    # undistorted radius (angle for fisheye) grid out to far beyond the corner
    top = np.pi / 2 * 0.999 if kind == "fisheye" else DISTORTION_FOV_FACTOR * corner
    x = np.linspace(0.0, top, 4097)
    g = _radial_map(kind, k, x)
    reach = np.nonzero(g >= corner)[0]
    stop = reach[0] if len(reach) else len(x) - 1
    d = np.diff(g[: stop + 1])
    if not np.all(np.isfinite(g[: stop + 1])) or not len(reach) or np.any(d <= 0):
        return (f"has the {model} distortion {k.tolist()}, which is not invertible over the image (the distorted "
                "radius stops growing before the image corner): undistortion is not defined there"), warning
    if x[stop] < corner / DISTORTION_FOV_FACTOR:
        return (f"has the {model} distortion {k.tolist()}, which shrinks the view to {x[stop] / corner:.2g} of its "
                f"size (more than a factor {DISTORTION_FOV_FACTOR:g}): a damaged or mis-scaled model"), warning
    return None, warning


def _data_lines(f: Path) -> list[tuple[int, list[str]]]:
    """(1-based line number, whitespace-split tokens) of every data line of a text model file,
    as COLMAP's reader takes them: comments and blank lines are skipped, except that in
    images.txt the line after each image line is its POINTS2D line, whatever it holds."""
    out = []
    points_line_next = False
    for n, line in enumerate(f.read_text(errors="replace").splitlines(), 1):
        if points_line_next:
            out.append((n, line.split()))
            points_line_next = False
            continue
        if line.strip().startswith("#") or not line.strip():
            continue
        out.append((n, line.split()))
        points_line_next = f.name == "images.txt"
    return out


def _numbers(f: Path, n: int, toks: list[str], what: str, cast=float) -> list:
    """``toks`` as numbers; a ValueError naming ``f:n`` if one is not a finite number."""
    try:
        vals = [cast(t) for t in toks]
    except ValueError:
        raise ValueError(f"{f}:{n}: {what} is not a number: {' '.join(toks)!r}") from None
    if cast is float and not all(np.isfinite(vals)):
        raise ValueError(f"{f}:{n}: {what} is not finite: {' '.join(toks)}; fix or re-export the model")
    return vals


def _check_text_model(model_dir: Path) -> int:
    """Check a text model line by line before pycolmap reads it (pycolmap's own checks abort
    with messages that name neither the file nor the line, or pass bad values silently).

    Checked: every number finite; image sizes and focal lengths positive; quaternions
    non-zero; every image's camera id defined in cameras.txt; image names without spaces
    (COLMAP's reader keeps a name only up to its first space) and plain file names
    (:func:`runtime.names.check_name`: a name becomes a path). Point ids that points3D.txt
    does not define are counted (the reader drops those observations with a warning).

    Returns:
        The number of observations naming a point id that points3D.txt lacks.

    Raises:
        ValueError: ``file:line: what is wrong``, with what to do.
    """
    cams_f, imgs_f, pts_f = (model_dir / n for n in ("cameras.txt", "images.txt", "points3D.txt"))
    camera_ids = set()
    if cams_f.is_file():
        for n, t in _data_lines(cams_f):
            if len(t) < 5:
                raise ValueError(f"{cams_f}:{n}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {' '.join(t)!r}")
            cid, = _numbers(cams_f, n, t[:1], "the camera id", int)
            w, h = _numbers(cams_f, n, t[2:4], "the image size", int)
            params = _numbers(cams_f, n, t[4:], f"camera {cid}'s parameters")
            if w <= 0 or h <= 0:
                raise ValueError(f"{cams_f}:{n}: camera {cid} has the image size {w}x{h}; sizes must be positive")
            check_image_size(w, h, f"{cams_f}:{n}: camera {cid}")
            k = _FOCALS.get(t[1], 0)
            bad = [v for v in params[:k] if v <= 0]
            if bad:
                raise ValueError(f"{cams_f}:{n}: camera {cid} ({t[1]}) has the focal length {bad[0]:g}; focal "
                                 "lengths must be positive (a negative one flips the image, zero collapses it)")
            refusal, warning = camera_problem(t[1], w, h, params)
            if refusal:
                raise ValueError(f"{cams_f}:{n}: camera {cid} ({t[1]}) {refusal}; fix or re-export the model")
            if warning:
                log.warning("%s:%d: camera %d (%s) %s", cams_f, n, cid, t[1], warning)
            if cid in camera_ids:
                raise ValueError(f"{cams_f}:{n}: camera id {cid} is defined twice; each camera id once")
            camera_ids.add(cid)
    point_ids = set()
    if pts_f.is_file():
        for n, t in _data_lines(pts_f):
            if len(t) < 8:
                raise ValueError(f"{pts_f}:{n}: expected POINT3D_ID X Y Z R G B ERROR TRACK[], got {' '.join(t)!r}")
            pid, = _numbers(pts_f, n, t[:1], "the point id", int)
            _numbers(pts_f, n, t[1:4], f"point {pid}'s position")
            rgb = _numbers(pts_f, n, t[4:7], f"point {pid}'s colour", int)
            if not all(0 <= c <= 255 for c in rgb):
                raise ValueError(f"{pts_f}:{n}: point {pid} has the colour {' '.join(t[4:7])}; colours are "
                                 "integers 0-255")
            _numbers(pts_f, n, t[7:8], f"point {pid}'s error")
            if (len(t) - 8) % 2:
                raise ValueError(f"{pts_f}:{n}: point {pid}'s TRACK must be (IMAGE_ID, POINT2D_IDX) pairs")
            if pid in point_ids:
                raise ValueError(f"{pts_f}:{n}: point id {pid} is defined twice; each point id once")
            point_ids.add(pid)
    missing = 0
    image_ids: dict[int, int] = {}
    names: dict[str, int] = {}
    if imgs_f.is_file():
        lines = _data_lines(imgs_f)
        for k in range(0, len(lines), 2):
            n, t = lines[k]
            if len(t) < 10:
                raise ValueError(f"{imgs_f}:{n}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {' '.join(t)!r}")
            if len(t) > 10:
                whole = " ".join(t[9:])
                raise ValueError(f"{imgs_f}:{n}: the image name {whole!r} contains spaces, which the COLMAP text "
                                 f"format cannot hold (COLMAP reads it as {t[9]!r}); rename the image file and "
                                 f"its entry, e.g. to {'_'.join(t[9:])!r}")
            check_name(t[9], "image name", f"{imgs_f}:{n}")  # it becomes a path: renders, images
            iid, = _numbers(imgs_f, n, t[:1], "the image id", int)
            q = _numbers(imgs_f, n, t[1:5], f"image {t[9]!r}'s quaternion")
            _numbers(imgs_f, n, t[5:8], f"image {t[9]!r}'s translation")
            cid, = _numbers(imgs_f, n, t[8:9], f"image {t[9]!r}'s camera id", int)
            if not np.linalg.norm(q) > 1e-12:
                raise ValueError(f"{imgs_f}:{n}: image {t[9]!r} has the zero quaternion {' '.join(t[1:5])}: "
                                 "no rotation; fix or re-export the model")
            if iid in image_ids:
                raise ValueError(f"{imgs_f}:{n}: image id {iid} is defined twice (also line {image_ids[iid]})")
            if t[9] in names:
                raise ValueError(f"{imgs_f}:{n}: the image {t[9]!r} appears twice (also line {names[t[9]]}): "
                                 "each image may appear once")
            image_ids[iid] = n
            names[t[9]] = n
            if cams_f.is_file() and cid not in camera_ids:
                raise ValueError(f"{imgs_f}:{n}: image {t[9]!r} uses camera {cid}, which {cams_f.name} does "
                                 f"not define (defined: {sorted(camera_ids)})")
            if k + 1 < len(lines):
                n2, obs = lines[k + 1]
                if len(obs) % 3:
                    raise ValueError(f"{imgs_f}:{n2}: POINTS2D of image {t[9]!r} must be (X, Y, POINT3D_ID) triples")
                _numbers(imgs_f, n2, obs[0::3] + obs[1::3], f"image {t[9]!r}'s 2D points")
                ids = _numbers(imgs_f, n2, obs[2::3], f"image {t[9]!r}'s point ids", int)
                missing += sum(1 for p in ids if p != -1 and p not in point_ids)
    return missing


def _check_read(model_dir: Path, rec) -> None:
    """The same checks on what pycolmap read (binary models have no lines to name)."""
    binary = (model_dir / "cameras.bin").is_file()
    for cid, cam in rec.cameras.items():
        params = np.asarray(cam.params, dtype=np.float64)
        k = _FOCALS.get(cam.model.name, 0)
        if not np.all(np.isfinite(params)) or np.any(params[:k] <= 0) or cam.width <= 0 or cam.height <= 0:
            raise ValueError(f"{model_dir}: camera {cid} ({cam.model.name} {cam.width}x{cam.height} "
                             f"{params.tolist()}) is not finite or has a non-positive size or focal length")
        check_image_size(cam.width, cam.height, f"{model_dir}: camera {cid}")
        if binary:  # a text model had these checks line by line
            refusal, warning = camera_problem(cam.model.name, cam.width, cam.height, params)
            if refusal:
                raise ValueError(f"{model_dir / 'cameras.bin'}: camera {cid} ({cam.model.name}) {refusal}; fix or "
                                 "re-export the model")
            if warning:
                log.warning("%s: camera %d (%s) %s", model_dir / "cameras.bin", cid, cam.model.name, warning)
    for iid, img in rec.images.items():
        if img.camera_id not in rec.cameras:
            raise ValueError(f"{model_dir}: image {img.name!r} uses camera {img.camera_id}, which the model "
                             "does not define")
        if img.has_pose:
            m = np.asarray(img.cam_from_world().matrix(), dtype=np.float64)
            if not np.all(np.isfinite(m)):
                raise ValueError(f"{model_dir}: image {img.name!r} has a non-finite pose (or a zero quaternion)")


def _one_format(model_dir: Path) -> None:
    """A folder with ``cameras.bin`` is read as a binary model: every other binary file
    must be there too, and text files beside it are named in a warning (they are not read)."""
    missing = [n for n in ("images.bin", "points3D.bin") if not (model_dir / n).is_file()]
    if missing:
        raise ValueError(f"{model_dir} holds cameras.bin but not {missing[0]}: a binary model needs cameras.bin, "
                         "images.bin and points3D.bin; copy or export the model again")
    text = [n for n in ("cameras.txt", "images.txt", "points3D.txt") if (model_dir / n).is_file()]
    if text:
        log.warning("%s holds both a binary and a text model (%s): reading the binary one (cameras.bin, "
                    "images.bin, points3D.bin); remove the files you do not mean", model_dir, ", ".join(text))


def read_model(path: str | Path, allow_distorted: bool = False) -> SparseModel:
    """Read a COLMAP model (text or binary) with pycolmap, checked.

    A text model is checked line by line first (:func:`_check_text_model`: finite values,
    positive sizes and focal lengths, non-zero quaternions, defined camera ids, names without
    spaces), then what pycolmap read (:func:`_check_read`; the only check a binary model
    gets). Errors name the file (and line); pycolmap's own messages show only with -v.
    Observations of point ids that points3D.txt lacks are dropped with a warning giving
    their count; a text model without points3D.txt is read as cameras only.

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
    text = not (model_dir / "cameras.bin").is_file()
    if not text:
        _one_format(model_dir)
        from camio.colmap_bin import check_binary_model

        check_binary_model(model_dir)  # every record fits: pycolmap never reads past or allocates blindly
    missing = _check_text_model(model_dir) if text else 0
    rec = pycolmap.Reconstruction()
    import tempfile

    with tempfile.TemporaryDirectory(prefix="camio_model_") as tmp:
        read_dir = model_dir
        if text and (model_dir / "images.txt").is_file() and not (model_dir / "points3D.txt").is_file():
            # cameras only: pycolmap wants all three files; the observations have no points
            log.warning("%s has no points3D.txt: reading the cameras only", model_dir)
            read_dir = Path(tmp)
            for name in ("cameras.txt", "images.txt"):
                (read_dir / name).write_bytes((model_dir / name).read_bytes())
            (read_dir / "points3D.txt").write_text("")
        try:
            rec.read(str(read_dir))
        except Exception as exc:  # pycolmap raises plain RuntimeError / ValueError / IndexError
            log.debug("pycolmap: %s", exc)
            raise ValueError(f"cannot read the COLMAP model in {model_dir}: damaged or inconsistent files "
                             "(-v shows pycolmap's message); copy or export the model again") from exc
    _check_text_counts(model_dir, rec)
    _check_read(model_dir, rec)
    if missing:
        log.warning("%s: %d observations name point ids that points3D.txt does not define; they are "
                    "dropped", model_dir / "images.txt", missing)

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
            if p2d.has_point3D() and p2d.point3D_id in row_of:
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
        if (model_dir / "cameras.bin").is_file():
            from camio.colmap_bin import check_binary_model

            check_binary_model(model_dir)  # never hand pycolmap a file whose counts overrun it
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
