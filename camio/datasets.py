"""Benchmark dataset layouts beside COLMAP / LLFF / transforms.json: detection and adapters,
and the registry of every dataset format (:data:`DATASET_FORMATS`: name, description, camera
files, reader, detection), which ``python -m camio convert --format``, auto-detection, the
workflow's config check and docs/contracts.md read.

Every adapter returns cameras in the project conventions (:mod:`camio`): ``cam_from_world``
float64, OpenCV axes (x right, y down, z forward), ``K`` in COLMAP pixel coordinates (the
top-left pixel centre is (0.5, 0.5)), sized to the image files actually read.

Layouts (what each reader expects; the conventions it converts):

* **DTU, IDR / MonoSDF / VolSDF / NeuS** (``dtu``): ``cameras.npz`` (or ``cameras_sphere.npz``)
  with ``world_mat_i`` (the 4x4 projection ``K [R | t]`` of DTU's calibration, world = DTU's
  metric frame) and optionally ``scale_mat_i`` (maps the normalised unit-sphere frame into the
  DTU frame). ``P = world_mat_i @ scale_mat_i`` is decomposed (RQ) into K, R and the camera
  centre, so the cameras are in the *normalised* frame, as IDR/MonoSDF use them. Images:
  IDR's ``image/NNNNNN.png`` (1600 x 1200, the frame the matrices are for) or MonoSDF's
  ``NNNNNN_rgb.png`` beside ``cameras.npz`` (its ``_depth``/``_normal`` maps and ``.npy`` files
  are not images of the scene and are ignored). MonoSDF's DTU images are 384 x 384: the
  1600 x 1200 frame centre-cropped to 1200 x 1200 (x offset 200 px) and resized by 384/1200;
  K is cropped and scaled the same way (``cx -= 200``; ``K[:2] *= 0.32``, exact in COLMAP pixel
  coordinates). Index i is the number in the file name.
* **MVSNet** (``mvsnet``; DTU/BlendedMVS/Tanks-and-Temples as MVSNet ships them):
  ``images/NNNNNNNN.jpg`` + ``cams/NNNNNNNN_cam.txt``: ``extrinsic`` then a 4x4 world-to-camera
  matrix (OpenCV axes, = cam_from_world), ``intrinsic`` then K (3x3) at the image files'
  resolution, then depth range values (ignored). A principal point far from the image centre
  (MVSNet's training cams are for 1/4 resolution) is refused rather than guessed.
* **Strecha** (``strecha``): ``images/NAME`` + ``gt_dense_cameras/NAME.camera`` (or the
  ``.camera`` files beside the images): 26 numbers: K (3x3 row-major), 3 radial distortion
  values, R (3x3, the camera-to-world rotation), C (the camera centre in world coordinates),
  width, height. So ``cam_from_world = [R^T | -R^T C]`` (P = K [R^T | -R^T C], as openMVG reads
  it). Non-zero distortion (k1, k2) is undistorted with ``undistort=True``; a third value is refused.

* **Middlebury multi-view** (``middlebury``; Seitz et al. CVPR 2006: temple, dino and their
  rings): the images beside one ``*_par.txt`` whose lines are ``NAME.png k11 .. k33 r11 .. r33
  t1 t2 t3``, the projection ``K [R | t]`` of that image (world -> OpenCV camera: R and t are
  ``cam_from_world``), K at the image files' resolution, image origin top-left (COLMAP's
  pixel coordinates). The dataset's first line is the number of images; a first line that is a
  header of names instead is skipped too.

Bare folders (``folder``) take only photographs: files whose names mark a depth, disparity,
normal, mask, confidence or alpha map are left out (with a warning naming how many), as are
single-channel 16-bit or float images; what remains must share one pixel type and one size
unless ``allow_mixed``. A folder holding camera files that no adapter reads is refused, naming
them (``format="folder"`` ignores them on purpose).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from camio.cameras import Camera
from camio.colmap import SparseModel, find_model_dir
from camio.images import image_size, list_images
from camio.limits import check_image_size

__all__ = ["DatasetFormat", "DATASET_FORMATS", "dataset_format", "detect_layout", "camera_like_files", "split_photos",
           "decompose_projection", "read_dtu", "read_mvsnet", "read_strecha", "read_middlebury", "DTU_FRAME",
           "source_camera_models"]

log = logging.getLogger(__name__)

DTU_FRAME = (1600, 1200)  # the image size DTU's projection matrices are for

_ROLE = re.compile(r"(^|[_\-.])(depth|depths|disp|disparity|normal|normals|mask|masks|conf|confidence|"
                   r"alpha|seg|segmentation|sem|semantic)s?([_\-.]|\d|$)", re.IGNORECASE)
_CAMERA_PATTERNS = ("*.camera", "*_cam.txt", "cam*.txt", "cameras*.npz", "cameras*.json", "transforms*.json",
                    "poses*.npy", "poses*.txt", "pose*.txt", "bundle*.out", "*.nvm", "*.sfm", "*.log",
                    "images.txt", "images.bin", "cameras.txt", "cameras.bin", "K.txt", "intrinsic*.txt",
                    "calib*.txt", "*.xmp", "*_par.txt")


class SceneError(ValueError):
    """A scene that cannot be loaded as given (the message says what to fix); raised by the
    readers here and by :mod:`camio.scene`, which imports them."""


def _scene_error(msg: str) -> Exception:
    return SceneError(msg)


# ------------------------------------------------------------------------------- detection
def camera_like_files(root: Path, depth: int = 2) -> list[Path]:
    """Files under ``root`` (itself and ``depth - 1`` levels below) whose names look like camera
    or pose files of some dataset (``*.camera``, ``*_cam.txt``, ``cameras*.npz``, ``*.log``, ...)."""
    found: list[Path] = []
    dirs = [root]
    for _ in range(depth):
        nxt = []
        for d in dirs:
            try:
                entries = sorted(d.iterdir())
            except OSError:
                continue
            for p in entries:
                if p.name.startswith("."):
                    continue
                if p.is_dir():
                    nxt.append(p)
                elif any(p.match(pat) for pat in _CAMERA_PATTERNS):
                    found.append(p)
        dirs = nxt
    return found


def _dtu_npz(root: Path) -> Path | None:
    for name in ("cameras.npz", "cameras_sphere.npz", "cameras_large.npz"):
        if (root / name).is_file():
            return root / name
    return None


def _strecha_dir(root: Path) -> Path | None:
    for d in (root / "gt_dense_cameras", root / "images", root):
        if d.is_dir() and any(d.glob("*.camera")):
            return d
    return None


def _middlebury_par(root: Path) -> Path | None:
    """The one ``*_par.txt`` of a Middlebury scene folder (None when there is none); several
    are refused (which one holds the cameras of these images is not for us to guess)."""
    pars = sorted(root.glob("*_par.txt"))
    if len(pars) > 1:
        raise _scene_error(f"{root} holds {len(pars)} Middlebury camera files ({', '.join(p.name for p in pars)}): "
                           "keep the one of these images")
    return pars[0] if pars else None


def detect_layout(root: Path) -> str:
    """The format of a scene folder from the camera files it holds: the first entry of
    :data:`DATASET_FORMATS` whose ``detect`` finds its files (transforms, colmap, llff, dtu,
    mvsnet, strecha, middlebury), else "folder" when no camera-like file is present.

    Raises:
        SceneError: camera-like files that no adapter reads (named in the message).
    """
    for fmt in DATASET_FORMATS.values():
        if fmt.detect is not None and fmt.detect(root):
            return fmt.name
    unknown = camera_like_files(root)
    if unknown:
        shown = ", ".join(str(p.relative_to(root)) for p in unknown[:5])
        known = ", ".join(f"{f.name} {f.files}" for f in DATASET_FORMATS.values() if f.cameras)
        raise _scene_error(
            f"{root} holds {len(unknown)} file(s) that look like camera or pose files ({shown}"
            f"{', ...' if len(unknown) > 5 else ''}) in a layout no camio adapter reads (known: {known}); "
            "convert them to COLMAP, or pass --format folder to ignore them")
    return "folder"


def source_camera_models(root: str | Path) -> list[str]:
    """COLMAP-style camera model names of a source scene without converting it, for planning
    (e.g. whether the workflow must undistort): a COLMAP model's models, "OPENCV" for a
    transforms.json or Strecha scene with distortion, "PINHOLE" otherwise; [] if unreadable."""
    root = Path(root)
    try:
        fmt = detect_layout(root) if root.is_dir() else "transforms"
    except ValueError:
        return []
    if fmt == "colmap":
        from camio.colmap import camera_model_names

        return camera_model_names(root)
    if fmt == "transforms":
        import json

        js = root if root.is_file() else (root / "transforms.json")
        if not js.is_file():
            return ["PINHOLE"]
        try:
            meta = json.loads(js.read_text())
        except (OSError, ValueError):
            return []
        keys = ("k1", "k2", "k3", "k4", "p1", "p2")
        blocks = [meta] + list(meta.get("frames") or [])
        dist = any(abs(float(b.get(k) or 0.0)) > 0 for b in blocks if isinstance(b, dict) for k in keys)
        return ["OPENCV"] if dist else ["PINHOLE"]
    if fmt == "strecha":
        d = _strecha_dir(root)
        for f in sorted(d.glob("*.camera")):
            try:
                vals = np.array(f.read_text().split(), np.float64)
            except (OSError, ValueError):
                return []
            if len(vals) >= 12 and np.any(vals[9:12] != 0):
                return ["OPENCV"]
        return ["PINHOLE"]
    return ["PINHOLE"]


# ----------------------------------------------------------------------------- bare folders
def _pixel_kind(path: Path) -> tuple[int, str]:
    """(channels, 'uint8' | 'uint16' | 'float') from the header."""
    import OpenImageIO as oiio

    from camio.images import _open

    inp = _open(path)
    try:
        spec = inp.spec()
        base = spec.format.basetype
        n = int(spec.nchannels)
    finally:
        inp.close()
    if base in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE):
        return n, "float"
    if base in (oiio.UINT16, oiio.INT16, oiio.UINT32, oiio.INT32):
        return n, "uint16"
    return n, "uint8"


def split_photos(image_dir: Path, names: list[str], allow_mixed: bool = False) -> list[str]:
    """The photographs among ``names`` (see the module docstring); warns about what is left out.

    Raises:
        SceneError: no photograph remains, or the remaining ones mix pixel types (gray / RGB,
            8-bit / 16-bit / float) and ``allow_mixed`` is False.
    """
    photos, by_name, by_type = [], [], []
    kinds: dict[str, list[str]] = {}
    for n in names:
        if _ROLE.search(Path(n).stem):
            by_name.append(n)
            continue
        ch, depth = _pixel_kind(image_dir / n)
        if ch in (1, 2) and depth != "uint8":
            by_type.append(n)
            continue
        kind = f"{'gray' if ch in (1, 2) else 'RGB'} {depth}"
        kinds.setdefault(kind, []).append(n)
        photos.append(n)
    if by_name:
        log.warning("%s: left out %d file(s) whose names mark depth/normal/mask/confidence maps, e.g. %s",
                    image_dir, len(by_name), by_name[:3])
    if by_type:
        log.warning("%s: left out %d single-channel 16-bit or float image(s) (depth-like data, not photographs), "
                    "e.g. %s", image_dir, len(by_type), by_type[:3])
    if not photos:
        raise _scene_error(f"{image_dir}: none of the {len(names)} image file(s) is a photograph "
                           f"({len(by_name)} named as depth/normal/mask/confidence maps, {len(by_type)} "
                           "single-channel 16-bit/float); point --src at the folder of the photographs")
    if len(kinds) > 1 and not allow_mixed:
        desc = "; ".join(f"{k}: {len(v)}, e.g. {v[0]}" for k, v in sorted(kinds.items()))
        raise _scene_error(f"{image_dir}: the images mix pixel types ({desc}); they look like different "
                           "kinds of data. Keep only the photographs, or pass --allow-mixed")
    return photos


# ------------------------------------------------------------------------------ maths
def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``P`` [3, 4] (any non-zero scale) -> (K [3, 3] with K[2, 2] = 1 and positive focal
    lengths, R [3, 3] proper rotation, C [3] camera centre) with P ~ K R [I | -C].

    Raises:
        ValueError: P is singular or not finite.
    """
    P = np.asarray(P, np.float64).reshape(3, 4)
    M = P[:, :3]
    if not np.all(np.isfinite(P)) or abs(np.linalg.det(M)) < 1e-300:
        raise ValueError("projection matrix is singular or not finite")
    if np.linalg.det(M) < 0:
        P, M = -P, -M
    # RQ of M via QR of the row-reversed transpose.
    flip = np.eye(3)[::-1]
    q, r = np.linalg.qr((flip @ M).T)
    K = flip @ r.T @ flip
    R = flip @ q.T
    s = np.diag(np.sign(np.diag(K)))
    K, R = K @ s, s @ R
    if np.linalg.det(R) < 0:  # cannot happen with det(M) > 0 and diag(K) > 0; kept as a guard
        raise ValueError("projection matrix decomposes into a reflection")
    C = -np.linalg.solve(M, P[:, 3])
    return K / K[2, 2], R, C


def _cam(name: str, w: int, h: int, K: np.ndarray, R: np.ndarray, C: np.ndarray) -> Camera:
    return Camera(name, w, h, K, np.concatenate([R, (-R @ C).reshape(3, 1)], 1))


def _numbers(path: Path) -> np.ndarray:
    try:
        return np.array(path.read_text().split(), np.float64)
    except (OSError, ValueError) as exc:
        raise _scene_error(f"cannot read camera file {path}: {exc}") from exc


# ------------------------------------------------------------------------------------ DTU
_DTU_NAME = re.compile(r"^(\d+)(_rgb)?\.(png|jpg|jpeg)$", re.IGNORECASE)


def dtu_images(root: Path) -> tuple[Path, list[str]]:
    """(image folder, names) of an IDR (``image/``) or MonoSDF (``*_rgb.png``) DTU scene."""
    for d in (root / "image", root / "images", root / "rgb"):
        if d.is_dir():
            names = [n for n in list_images(d) if _DTU_NAME.match(n) and not _ROLE.search(Path(n).stem)]
            if names:
                return d, names
    names = [n for n in list_images(root) if _DTU_NAME.match(n) and n.lower().split(".")[0].endswith("_rgb")]
    if names:
        return root, names
    raise _scene_error(f"{root}: cameras.npz found but no DTU images (image/NNNNNN.png as in IDR, or "
                       "NNNNNN_rgb.png as in MonoSDF)")


def read_dtu(root: Path, image_dir: Path | None = None, names: list[str] | None = None) -> tuple[Path, list[str], SparseModel]:
    """Cameras of a DTU scene in the IDR / MonoSDF layout (module docstring), in the frame
    normalised by ``scale_mat_i``, sized (and for MonoSDF's square images cropped) to the files."""
    npz = _dtu_npz(root)
    if npz is None:
        raise _scene_error(f"{root}: no cameras.npz")
    if image_dir is None or names is None:
        image_dir, names = dtu_images(root)
    try:
        data = dict(np.load(npz, allow_pickle=False))
    except (OSError, ValueError) as exc:
        raise _scene_error(f"cannot read {npz}: {exc}") from exc
    W0, H0 = DTU_FRAME
    cams = []
    for n in names:
        m = _DTU_NAME.match(n)
        if m is None:
            raise _scene_error(f"{image_dir / n}: a DTU image name must be NNNNNN.png or NNNNNN_rgb.png")
        i = int(m.group(1))
        if f"world_mat_{i}" not in data:
            raise _scene_error(f"{npz} has no world_mat_{i} for image {n}")
        P = np.asarray(data[f"world_mat_{i}"], np.float64)
        S = np.asarray(data.get(f"scale_mat_{i}", np.eye(4)), np.float64)
        try:
            K, R, C = decompose_projection((P @ S)[:3, :4])
        except ValueError as exc:
            raise _scene_error(f"{npz}: world_mat_{i} @ scale_mat_{i}: {exc}") from exc
        w, h = image_size(image_dir / n)
        if (w, h) == (W0, H0):
            pass
        elif abs(w / h - W0 / H0) < 1e-3:
            K = K.copy()
            K[0] *= w / W0
            K[1] *= h / H0
        elif w == h:  # MonoSDF's center_crop_for_dtu: crop H0 x H0 from the middle, resize
            K = K.copy()
            K[0, 2] -= (W0 - H0) / 2
            K[:2] *= w / H0
        else:
            raise _scene_error(f"{image_dir / n} is {w}x{h}: neither DTU's {W0}x{H0} frame, a uniform "
                               "rescale of it, nor MonoSDF's square centre crop")
        cams.append(_cam(n, w, h, K, R, C))
    return image_dir, names, SparseModel(cams)


# --------------------------------------------------------------------------------- MVSNet
def read_mvsnet_cam(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(cam_from_world [4, 4], K [3, 3]) from one MVSNet ``*_cam.txt``."""
    try:
        lines = path.read_text().split("\n")
        words = [ln.strip().lower() for ln in lines]
        e = words.index("extrinsic")
        k = words.index("intrinsic")
        E = np.array(" ".join(lines[e + 1:e + 5]).split(), np.float64).reshape(4, 4)
        K = np.array(" ".join(lines[k + 1:k + 4]).split(), np.float64).reshape(3, 3)
    except (OSError, ValueError) as exc:
        raise _scene_error(f"{path}: not an MVSNet camera file ('extrinsic' + 4x4, 'intrinsic' + 3x3): "
                           f"{exc}") from exc
    if not (np.all(np.isfinite(E)) and np.all(np.isfinite(K))):
        raise _scene_error(f"{path}: non-finite camera values")
    return E, K


def read_mvsnet(root: Path, image_dir: Path, names: list[str]) -> SparseModel:
    """Cameras of an MVSNet scene: image ``STEM.ext`` <-> ``cams/STEM_cam.txt``."""
    cams = []
    missing = []
    for n in names:
        f = root / "cams" / f"{Path(n).stem}_cam.txt"
        if not f.is_file():
            missing.append(n)
            continue
        E, K = read_mvsnet_cam(f)
        w, h = image_size(image_dir / n)
        if abs(K[0, 2] - w / 2) > 0.25 * w or abs(K[1, 2] - h / 2) > 0.25 * h:
            raise _scene_error(f"{f}: principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) is far from the centre "
                               f"of the {w}x{h} image {n}: the intrinsics are for another resolution "
                               "(MVSNet training cams are for 1/4 size); use cams matching the images")
        cams.append(Camera(n, w, h, K, E[:3]))
    if missing:
        raise _scene_error(f"{len(missing)} of {len(names)} image(s) in {image_dir} have no cams/<stem>_cam.txt, "
                           f"e.g. {missing[:3]}")
    return SparseModel(cams)


# -------------------------------------------------------------------------------- Strecha
def read_strecha_camera(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, int]:
    """(K, distortion [3], R camera-to-world, C, width, height) from one Strecha ``.camera``."""
    v = _numbers(path)
    if len(v) != 26:
        raise _scene_error(f"{path}: a Strecha .camera file holds 26 numbers (K, 3 distortion, R, C, W H), "
                           f"found {len(v)}")
    K, dist, R, C = v[:9].reshape(3, 3), v[9:12], v[12:21].reshape(3, 3), v[21:24]
    w, h = int(round(v[24])), int(round(v[25]))
    if not np.all(np.isfinite(v)) or abs(np.linalg.det(R) - 1) > 1e-3:
        raise _scene_error(f"{path}: R is not a rotation (det {np.linalg.det(R):.4f}) or values are not finite")
    if w <= 0 or h <= 0:
        raise _scene_error(f"{path}: the image size {w}x{h} is not positive")
    check_image_size(w, h, str(path))
    return K, dist, R, C, w, h


def read_strecha(root: Path, image_dir: Path, names: list[str]) -> SparseModel:
    """Cameras of a Strecha scene at the size the .camera files state (the caller rescales
    to the image files). Distortion (k1, k2) is kept as an OPENCV camera model."""
    cdir = _strecha_dir(root)
    if cdir is None:
        raise _scene_error(f"{root}: --format strecha needs the .camera files (in gt_dense_cameras/, images/ or "
                           "the scene folder itself); none found")
    cams, models, missing = [], {}, []
    for n in names:
        f = cdir / f"{n}.camera"
        if not f.is_file():
            missing.append(n)
            continue
        K, dist, Rc2w, C, w, h = read_strecha_camera(f)
        if dist[2] != 0:
            raise _scene_error(f"{f}: a third distortion coefficient ({dist[2]}) is not supported")
        R = Rc2w.T
        cams.append(_cam(n, w, h, K, R, C))
        if np.any(dist != 0):
            models[n] = ("OPENCV", np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist[0], dist[1], 0.0, 0.0]))
        else:
            models[n] = ("PINHOLE", np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    if missing:
        raise _scene_error(f"{len(missing)} of {len(names)} image(s) in {image_dir} have no {cdir}/<name>.camera, "
                           f"e.g. {missing[:3]}")
    return SparseModel(cams, camera_models=models)


# ----------------------------------------------------------------------------- Middlebury
def read_middlebury_par(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Image name -> (K [3, 3], cam_from_world [3, 4]) from a Middlebury ``*_par.txt``."""
    try:
        lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    except OSError as exc:
        raise _scene_error(f"cannot read camera file {path}: {exc}") from exc
    if lines and (len(lines[0]) == 1 or len(lines[0]) == 22 and not _is_number(lines[0][1])):
        lines = lines[1:]  # the dataset's count line, or a header of names
    cams = {}
    for i, words in enumerate(lines, 1):
        if len(words) != 22:
            raise _scene_error(f"{path}: camera line {i} holds {len(words)} fields; a Middlebury line is "
                               "'NAME k11 .. k33 r11 .. r33 t1 t2 t3' (22)")
        try:
            v = np.array(words[1:], np.float64)
        except ValueError as exc:
            raise _scene_error(f"{path}: camera line {i} ({words[0]}): {exc}") from exc
        K, R, t = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:21]
        if not np.all(np.isfinite(v)) or np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
            raise _scene_error(f"{path}: camera line {i} ({words[0]}): R is not a rotation or values are not finite")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1) > 1e-9 or np.any(K[2, :2] != 0):
            raise _scene_error(f"{path}: camera line {i} ({words[0]}): K is not an intrinsic matrix "
                               "(positive focal lengths, last row 0 0 1)")
        if words[0] in cams:
            raise _scene_error(f"{path}: image {words[0]} has two camera lines")
        cams[words[0]] = (K, np.concatenate([R, t.reshape(3, 1)], 1))
    return cams


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def read_middlebury(root: Path, image_dir: Path, names: list[str]) -> SparseModel:
    """Cameras of a Middlebury scene (module docstring) for the images ``names``: K as the
    calibration gives it, which is for the image files as the dataset ships them."""
    par = _middlebury_par(root)
    if par is None:
        raise _scene_error(f"{root} holds no Middlebury *_par.txt")
    table = read_middlebury_par(par)
    missing = [n for n in names if n not in table]
    if missing:
        raise _scene_error(f"{len(missing)} of {len(names)} image(s) in {image_dir} have no line in {par}, "
                           f"e.g. {missing[:3]}")
    cams = []
    for n in names:
        K, cw = table[n]
        w, h = image_size(image_dir / n)
        cams.append(Camera(n, w, h, K, cw))
    return SparseModel(cams)


# ------------------------------------------------------------------------------- the registry
def _has_colmap_model(root: Path) -> bool:
    try:
        find_model_dir(root)
        return True
    except FileNotFoundError:
        return False


@dataclass(frozen=True)
class DatasetFormat:
    """One dataset format ``python -m camio convert --format`` reads.

    Attributes:
        name: the ``--format`` value, the config's ``scene.format`` and ``scene.json``'s ``format``.
        description: one line: what the layout is (``convert --help`` and docs/contracts.md).
        files: the camera files it reads, as the refusal of an unknown layout names them.
        cameras: its source carries reference cameras (the workflow evaluates poses and held-out
            views of such a scene; a folder of photos has none).
        detect: ``folder -> bool``, whether auto-detection takes a folder as this format (asked in
            the order of :data:`DATASET_FORMATS`); None: only by name (``folder`` is the fallback).
        read: ``(root, image_dir, names) -> SparseModel``, the reference cameras of ``names``
            (world -> OpenCV camera, ``K`` at the image files' resolution); None: camio.scene
            loads it itself (COLMAP, LLFF, transforms.json, DTU, folder: their own image rules).
        distortion: ``read`` may return OPENCV distortion, undistorted with ``--undistort``.
    """

    name: str
    description: str
    files: str
    cameras: bool
    detect: Callable[[Path], bool] | None = None
    read: Callable[[Path, Path, list[str]], SparseModel] | None = None
    distortion: bool = False


#: every dataset format by name, in the order auto-detection asks them (docs/contracts.md,
#: "Adding a dataset format")
DATASET_FORMATS: dict[str, DatasetFormat] = {f.name: f for f in (
    DatasetFormat("transforms", "instant-ngp / nerfstudio / NeRF-synthetic camera-to-world poses (OpenGL axes)",
                  "transforms.json", True,
                  lambda r: (r / "transforms.json").is_file() or (r / "transforms_train.json").is_file()),
    DatasetFormat("colmap", "a COLMAP model, text or binary (distorted models undistorted with --undistort)",
                  "sparse/0", True, _has_colmap_model),
    DatasetFormat("llff", "LLFF: per image a 3x5 pose-and-intrinsics matrix and two depth bounds",
                  "poses_bounds.npy", True, lambda r: (r / "poses_bounds.npy").is_file()),
    DatasetFormat("dtu", "DTU as IDR / MonoSDF / VolSDF / NeuS ship it: projection and scale matrices",
                  "cameras.npz", True, lambda r: _dtu_npz(r) is not None),
    DatasetFormat("mvsnet", "DTU / BlendedMVS / Tanks-and-Temples as MVSNet ships them: extrinsic and intrinsic",
                  "cams/*_cam.txt", True,
                  lambda r: (r / "cams").is_dir() and any((r / "cams").glob("*_cam.txt")), read_mvsnet),
    DatasetFormat("strecha", "Strecha et al.'s multi-view sets: K, radial distortion, R and the camera centre",
                  "*.camera", True, lambda r: _strecha_dir(r) is not None, read_strecha, distortion=True),
    DatasetFormat("middlebury", "Middlebury multi-view (temple, dino): the projection K [R t] of each image",
                  "*_par.txt", True, lambda r: _middlebury_par(r) is not None, read_middlebury),
    DatasetFormat("folder", "a bare folder of photographs, no cameras (maps and masks left out)",
                  "(none)", False),
)}


def dataset_format(name: str) -> DatasetFormat:
    """The format called ``name`` (:class:`SceneError` naming the known ones otherwise)."""
    try:
        return DATASET_FORMATS[name]
    except KeyError:
        raise _scene_error(f"unknown scene format {name!r}; choose one of auto, {', '.join(DATASET_FORMATS)}") from None
