"""Scenes: an image folder, its sorted image names and optional reference cameras / points.

Readers convert every input format to the project conventions (:mod:`camio`):

* COLMAP model (text or binary, via :func:`camio.colmap.read_model`). PINHOLE /
  SIMPLE_PINHOLE are used directly; SIMPLE_RADIAL, RADIAL, OPENCV are undistorted to PINHOLE
  with pycolmap's undistorter when ``undistort=True`` (:mod:`camio.undistort`), refused
  otherwise.
* LLFF ``poses_bounds.npy``: [N, 17] = per image a 3x5 matrix [R | t | (H, W, focal)] with
  R's columns the camera's [down, right, back] axes in world coordinates and t the camera
  centre, plus two depth bounds. Rows follow the sorted image names.
* ``transforms.json`` (instant-ngp / nerfstudio): camera-to-world in OpenGL axes (x right,
  y up, z back); intrinsics ``fl_x``/``fl_y``/``cx``/``cy`` or ``camera_angle_x`` (and
  ``camera_angle_y``), global or per frame; pixel coordinates as in COLMAP.
* DTU (IDR / MonoSDF ``cameras.npz``), MVSNet ``cams/*_cam.txt``, Strecha ``*.camera`` and
  Middlebury ``*_par.txt``:
  :mod:`camio.datasets`, which also holds the auto-detection and the bare-folder rules.
* A bare image folder (no cameras): photographs only (:func:`camio.datasets.split_photos`).

Distortion (COLMAP SIMPLE_RADIAL / RADIAL / OPENCV, transforms.json ``k1 k2 p1 p2``, Strecha
``k1 k2``) is removed with pycolmap's undistorter when ``undistort=True`` and refused otherwise.

Intrinsics are always rescaled to the size of the images actually found in the folder (e.g.
a full-resolution model used with ``images_8``), per image, from the file headers.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from camio.cameras import Camera, invert_cam_from_world, opengl_to_opencv_c2w, scale_intrinsics
from camio.colmap import PINHOLE_MODELS, SparseModel, UnsupportedCameraModelError, \
    find_model_dir, read_model
from camio.datasets import DATASET_FORMATS, SceneError, dataset_format, detect_layout, dtu_images, read_dtu, \
    split_photos
from camio.arrays import check_npy
from camio.images import image_size, list_images, read_image
from camio.limits import check_image_size
from runtime.checks import folder_problem

__all__ = ["Scene", "SceneError", "load_scene", "detect_format", "check_same_size", "read_llff_poses",
           "llff_to_cam_from_world", "FORMATS", "REFERENCE_FORMATS", "UNDISTORTABLE_MODELS"]

log = logging.getLogger(__name__)

# the --format values: auto-detection, then every format of the registry (camio.datasets)
FORMATS = ("auto", *DATASET_FORMATS)
# the formats whose source carries reference cameras
REFERENCE_FORMATS = tuple(n for n, f in DATASET_FORMATS.items() if f.cameras)
UNDISTORTABLE_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class Scene:
    """Images plus optional reference cameras.

    Attributes:
        image_dir: folder the image names are relative to.
        names: sorted image names (relative paths, '/' separated).
        model: reference cameras (for some or all names; sizes match the image files) and
            optional points, or None.
        source_format: one of :data:`FORMATS` (not "auto").
        source: the path the scene was loaded from.
        undistorted: True if the images and model are the output of the undistorter.
        source_models: camera models of the source as read (e.g. ("OPENCV",)), before any
            undistortion; () without cameras.
    """

    image_dir: Path
    names: list[str]
    model: SparseModel | None
    source_format: str
    source: Path
    undistorted: bool = False
    source_models: tuple[str, ...] = ()

    def describe(self) -> str:
        """One line for the user: format, image count, cameras and their model."""
        n = 0 if self.model is None else len(self.model.cameras)
        cams = (f"{n} reference cameras ({'/'.join(self.source_models) or 'PINHOLE'}"
                f"{', undistorted to PINHOLE' if self.undistorted else ''})" if n else "no reference cameras")
        return f"detected format {self.source_format}: {len(self.names)} images, {cams}"

    def image_path(self, name: str) -> Path:
        return self.image_dir / name

    def sizes(self) -> dict[str, tuple[int, int]]:
        """name -> (width, height) from the file headers (display orientation)."""
        return {n: image_size(self.image_path(n)) for n in self.names}

    def __len__(self) -> int:
        return len(self.names)


def check_same_size(image_dir: str | Path, names: list[str]) -> tuple[int, int]:
    """(width, height) shared by all ``names`` in ``image_dir``.

    Raises:
        SceneError: the images have different sizes (lists each size with an example).
    """
    sizes: dict[tuple[int, int], list[str]] = {}
    for n in names:
        sizes.setdefault(image_size(Path(image_dir) / n), []).append(n)
    if len(sizes) != 1:
        desc = "; ".join(f"{w}x{h}: {len(v)} image(s), e.g. {v[0]}" for (w, h), v in sorted(sizes.items()))
        raise SceneError(f"images in {image_dir} have mixed sizes ({desc}); one size is required: "
                         "resize or crop them to a common size")
    return next(iter(sizes))


def detect_format(path: str | Path) -> str:
    """Guess the format of ``path`` (a file or a scene folder); see :func:`load_scene`."""
    p = Path(path)
    if p.is_file():
        if p.suffix == ".json":
            return "transforms"
        if p.name.endswith(".npy"):
            return "llff"
        raise SceneError(f"{p} is a file but neither a transforms .json nor poses_bounds.npy")
    if not p.is_dir():
        raise SceneError(f"scene path {p} does not exist")
    return detect_layout(p)


def _resolve_images(root: Path, images_subdir: str | Path | None) -> Path:
    if images_subdir is not None:
        d = Path(images_subdir)
        d = d if d.is_absolute() else root / d
        problem = folder_problem(d, "image folder")
        if problem:
            raise SceneError(problem)
        return d
    if (root / "images").is_dir():
        return root / "images"
    return root


def _image_names(image_dir: Path) -> list[str]:
    names = list_images(image_dir)
    if not names:
        raise SceneError(f"no images (.png/.jpg/.jpeg/.tif/.tiff/.exr) in {image_dir}; point the "
                         "loader at the scene folder or its image folder")
    return names


def _fit_to_images(model: SparseModel, image_dir: Path, names: list[str]) -> SparseModel:
    """Check every model image exists; rescale cameras (and observations) to the file sizes."""
    present = set(names)
    missing = [c.name for c in model.cameras if c.name not in present]
    if missing:
        raise SceneError(f"the model names {len(missing)} image(s) missing from {image_dir}, e.g. "
                         f"{missing[:3]}; use the matching image folder (--images-subdir)")
    cams, obs = [], {}
    for c in model.cameras:
        w, h = image_size(image_dir / c.name)
        if (w, h) == (c.width, c.height):
            cams.append(c)
            if c.name in model.observations:
                obs[c.name] = model.observations[c.name]
            continue
        sx, sy = w / c.width, h / c.height
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise SceneError(f"image {c.name} is {w}x{h} but its camera is {c.width}x{c.height}: "
                             "not a uniform rescale (cropped?)")
        cams.append(Camera(c.name, w, h, scale_intrinsics(c.K, sx, sy), c.cam_from_world))
        if c.name in model.observations:
            xy, idx = model.observations[c.name]
            obs[c.name] = (xy * np.array([sx, sy]), idx)
    if any(c is not m for c, m in zip(cams, model.cameras)):
        log.info("rescaled reference intrinsics to the image sizes found in %s", image_dir)
    return SparseModel(cams, model.points, model.colors, obs, model.camera_models)


def _verify_readable(image_dir: Path, names: list[str]) -> None:
    from runtime.logs import progress

    for n in progress(names, desc="verify images"):
        read_image(image_dir / n)  # raises ImageReadError naming the file


def load_scene(
    path: str | Path,
    format: str = "auto",
    images_subdir: str | Path | None = None,
    undistort: bool = False,
    work_dir: str | Path | None = None,
    verify_images: bool = True,
    allow_mixed: bool = False,
    skip_missing: bool = False,
) -> Scene:
    """Load a scene in any supported format.

    Args:
        path: scene folder, a COLMAP model folder, a ``transforms*.json`` or a
            ``poses_bounds.npy``.
        format: one of :data:`FORMATS`; "auto" detects from the camera files present
            (:func:`camio.datasets.detect_layout`); a folder with camera files no adapter
            reads is an error naming them.
        images_subdir: image folder relative to the scene folder (or absolute); default
            ``images`` if present, else the folder itself (transforms: its folder).
        undistort: undistort distorted cameras (COLMAP SIMPLE_RADIAL / RADIAL / OPENCV,
            transforms.json or Strecha distortion) to PINHOLE with pycolmap (needs ``work_dir``,
            where the undistorted images go); if False a distorted model raises
            :class:`UnsupportedCameraModelError`.
        work_dir: output folder for undistorted images and model (created; must be empty).
        verify_images: decode every image once so that a truncated file fails here.
        allow_mixed: a bare folder may mix pixel types (gray / RGB, 8 / 16 bit).
        skip_missing: transforms.json frames whose image files are missing are dropped with a
            warning (default: an error naming how many are missing).

    Raises:
        SceneError, UnsupportedCameraModelError, ImageReadError: with what to fix.
    """
    if format != "auto":
        dataset_format(format)  # an unknown name: SceneError naming the known ones
    path = Path(path)
    if not path.exists():
        raise SceneError(f"scene path {path} does not exist")
    fmt = detect_format(path) if format == "auto" else format
    root = path.parent if path.is_file() else path
    if fmt == "transforms":
        scene = _load_transforms(path, images_subdir, skip_missing)
        scene = _maybe_undistort(scene, undistort, work_dir)
    elif fmt == "dtu":
        if images_subdir is not None:
            image_dir = _resolve_images(root, images_subdir)
            image_dir, names = dtu_images(image_dir) if not (image_dir / "cameras.npz").exists() else (
                image_dir, _image_names(image_dir))
            image_dir, names, model = read_dtu(root, image_dir, names)
        else:
            image_dir, names, model = read_dtu(root)
        scene = Scene(image_dir, names, model, "dtu", path, source_models=("PINHOLE",))
    else:
        image_dir = _resolve_images(root, images_subdir)
        names = _image_names(image_dir)
        if fmt == "folder":
            scene = Scene(image_dir, split_photos(image_dir, names, allow_mixed), None, "folder", path)
        elif fmt == "llff":
            npy = path if path.is_file() else root / "poses_bounds.npy"
            scene = Scene(image_dir, names, _fit_to_images(read_llff_poses(npy, names, image_dir), image_dir, names),
                          "llff", path, source_models=("PINHOLE",))
        elif fmt == "colmap":
            scene = _load_colmap(path, image_dir, names, undistort, work_dir)
        else:  # a format of the registry with a reader (mvsnet, strecha, middlebury, ...)
            reader = dataset_format(fmt)
            if reader.read is None:  # pragma: no cover - every format without a reader is loaded above
                raise SceneError(f"scene format {fmt!r} has no reader in camio.datasets.DATASET_FORMATS")
            model = reader.read(root, image_dir, names)
            if reader.distortion:
                scene = Scene(image_dir, names, _fit_distorted(model, image_dir, names), fmt, path)
                scene = _maybe_undistort(scene, undistort, work_dir)
            else:
                scene = Scene(image_dir, names, model, fmt, path, source_models=("PINHOLE",))
    if verify_images:
        _verify_readable(scene.image_dir, scene.names)
    n_cams = 0 if scene.model is None else len(scene.model.cameras)
    log.info("loaded %s scene %s: %d images, %d reference cameras, %d points", scene.source_format, path,
             len(scene.names), n_cams, 0 if scene.model is None else len(scene.model.points))
    return scene


def _fit_distorted(model: SparseModel, image_dir: Path, names: list[str]) -> SparseModel:
    """:func:`_fit_to_images`, also rescaling the pinhole part of the distorted camera models
    (distortion coefficients act on normalised coordinates and stay)."""
    fitted = _fit_to_images(model, image_dir, names)
    models = {}
    for c in fitted.cameras:
        m, params = model.camera_models.get(c.name, ("PINHOLE", None))
        params = np.r_[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2],
                       (params[4:] if params is not None and m == "OPENCV" else [])]
        models[c.name] = (m, params)
    return SparseModel(fitted.cameras, fitted.points, fitted.colors, fitted.observations, models)


def _maybe_undistort(scene: Scene, undistort: bool, work_dir: str | Path | None) -> Scene:
    """Refuse or undistort a scene whose ``model.camera_models`` hold OPENCV distortion."""
    models = scene.model.camera_models if scene.model is not None else {}
    kinds = tuple(sorted({m for m, _ in models.values()})) or ("PINHOLE",)
    scene.source_models = kinds
    distorted = [n for n, (m, p) in models.items() if m == "OPENCV" and np.any(p[4:] != 0)]
    if not distorted:
        return scene
    if not undistort:
        ex = distorted[0]
        raise UnsupportedCameraModelError(
            f"{scene.source}: {len(distorted)} camera(s) have lens distortion (OPENCV k1 k2 p1 p2 = "
            f"{models[ex][1][4:].tolist()} for {ex}); pass undistort=True (`python -m camio convert "
            "--undistort`) to undistort the images to PINHOLE with pycolmap")
    if work_dir is None:
        raise SceneError("undistort=True needs a work_dir to write the undistorted images into")
    from camio.undistort import undistort_model

    out_images, out_model = undistort_model(scene.model, scene.image_dir, Path(work_dir))
    und = read_model(out_model)
    und_names = _image_names(out_images)
    return Scene(out_images, und_names, _fit_to_images(und, out_images, und_names), scene.source_format,
                 scene.source, undistorted=True, source_models=kinds)


def _load_colmap(path: Path, image_dir: Path, names: list[str], undistort: bool,
                 work_dir: str | Path | None) -> Scene:
    model = read_model(path, allow_distorted=True)
    kinds = {m for m, _ in model.camera_models.values()}
    unsupported = sorted(kinds - set(PINHOLE_MODELS) - set(UNDISTORTABLE_MODELS))
    if unsupported:
        raise UnsupportedCameraModelError(
            f"COLMAP model {path} uses camera model(s) {unsupported}; supported are "
            f"{', '.join(PINHOLE_MODELS + UNDISTORTABLE_MODELS)} (re-run COLMAP with one of them)")
    distorted = sorted(kinds - set(PINHOLE_MODELS))
    if not distorted:
        return Scene(image_dir, names, _fit_to_images(model, image_dir, names), "colmap", path,
                     source_models=tuple(sorted(kinds)))
    if not undistort:
        raise UnsupportedCameraModelError(
            f"COLMAP model {path} uses the distorted camera model(s) {distorted}; pass undistort=True "
            "(`python -m camio convert --undistort`) to undistort the images to PINHOLE with pycolmap")
    if work_dir is None:
        raise SceneError("undistort=True needs a work_dir to write the undistorted images into")
    _fit_to_images(model, image_dir, names)  # missing images fail before the undistorter runs
    from camio.undistort import undistort_colmap

    out_images, out_model = undistort_colmap(find_model_dir(path), image_dir, Path(work_dir))
    und = read_model(out_model)
    und_names = _image_names(out_images)
    return Scene(out_images, und_names, _fit_to_images(und, out_images, und_names), "colmap", path,
                 undistorted=True, source_models=tuple(sorted(kinds)))


# ---------------------------------------------------------------------------------------- LLFF
# NeX's intrinsics file beside a [N, 14] poses_bounds.npy (read_llff_poses)
NEX_INTRINSICS = "hwf_cxcy.npy"


def llff_to_cam_from_world(poses: np.ndarray) -> np.ndarray:
    """LLFF camera-to-world [N, 3, 4|5] ([down, right, back] axes) -> cam_from_world [N, 3, 4].

    The OpenCV camera axes are right = LLFF column 1, down = column 0, forward = -column 2.
    """
    p = np.asarray(poses, np.float64)[..., :4]
    c2w = np.concatenate([p[..., 1:2], p[..., 0:1], -p[..., 2:3], p[..., 3:4]], axis=-1)
    return invert_cam_from_world(c2w)[..., :3, :]


def read_llff_poses(npy: str | Path, names: list[str], image_dir: Path | None = None) -> SparseModel:
    """Cameras from ``poses_bounds.npy`` for the sorted ``names``.

    LLFF's rows [N, 17] hold a 3x5 matrix per image, the camera-to-world pose in its [down,
    right, back] axes beside (H, W, focal), then the two depth bounds: K = [[f, 0, W/2], [0, f,
    H/2], [0, 0, 1]] at W x H (LLFF's principal point is the image centre). NeX's layout (its
    Shiny dataset, Wizadwongsa et al. CVPR 2021) keeps rows [N, 14], the 3x4 pose in the same
    axes and the bounds, and one ``hwf_cxcy.npy`` beside the file, (H, W, fx, fy, cx, cy) shared
    by every image. :func:`load_scene` rescales K to the image files.
    """
    npy = Path(npy)
    if not npy.is_file():
        raise SceneError(f"no LLFF poses file {npy}")
    try:
        check_npy(npy)  # before numpy allocates what the header claims
        arr = np.load(npy, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise SceneError(f"{npy}: not a readable poses_bounds.npy ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] not in (14, 15, 17):
        raise SceneError(f"{npy}: expected an [N, 17] poses_bounds array (or NeX's [N, 14]), got shape {arr.shape}")
    if len(arr) != len(names):
        raise SceneError(f"{npy} holds {len(arr)} poses but {image_dir or 'the image folder'} has "
                         f"{len(names)} images; LLFF poses follow the sorted image names one to one")
    if arr.shape[1] == 14:
        poses = arr[:, :12].reshape(-1, 3, 4)
        h, w, fx, fy, cx, cy = _nex_intrinsics(npy.parent / NEX_INTRINSICS, npy)
        intrinsics = [(h, w, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])) for _ in range(len(arr))]
    else:
        poses = arr[:, :15].reshape(-1, 3, 5)
        intrinsics = [(h, w, np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])) for h, w, f in poses[:, :, 4]]
    for h, w, _ in intrinsics:
        if not (np.isfinite(h) and np.isfinite(w) and h >= 1 and w >= 1):
            raise SceneError(f"{npy}: the image size {w}x{h} (H, W of the poses) is not a positive number")
        check_image_size(int(round(w)), int(round(h)), str(npy))
    cfw = llff_to_cam_from_world(poses)
    return SparseModel([Camera(name, int(round(w)), int(round(h)), K, m)
                        for name, (h, w, K), m in zip(sorted(names), intrinsics, cfw)])


def _nex_intrinsics(path: Path, npy: Path) -> tuple[float, ...]:
    """(H, W, fx, fy, cx, cy) from NeX's ``hwf_cxcy.npy`` (6 numbers)."""
    if not path.is_file():
        raise SceneError(f"{npy}: rows of 14 are NeX's layout, whose intrinsics are in {path.name} beside it; "
                         f"there is no {path}")
    try:
        check_npy(path)
        v = np.load(path, allow_pickle=False).astype(np.float64).reshape(-1)
    except (ValueError, OSError, EOFError) as exc:
        raise SceneError(f"{path}: not a readable {NEX_INTRINSICS} ({exc})") from None
    if v.size != 6 or not np.all(np.isfinite(v)) or v[:4].min() <= 0:
        raise SceneError(f"{path}: expected 6 finite numbers H, W, fx, fy, cx, cy (H, W, fx, fy > 0), got "
                         f"{v.size} values {v.tolist()[:6]}")
    return tuple(float(x) for x in v)


# ---------------------------------------------------------------------------------- transforms
def _find_frame_file(base: Path, file_path: object, json_path: Path) -> Path | None:
    """The image a frame names (``file_path`` may omit the extension, as NeRF-synthetic's
    ``./train/r_0`` does), or None when no such file exists. The path must stay inside the
    scene's folder ``base`` (:func:`runtime.names.check_inside`: ``../`` and absolute paths
    elsewhere are refused)."""
    from runtime.names import check_inside

    try:
        p = check_inside(file_path, base, "frame file_path", json_path).resolve()
    except ValueError as exc:
        raise SceneError(str(exc)) from None
    if p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".exr", ".tif"):
        cand = p.with_name(p.name + ext)
        if cand.is_file():
            return cand
    return None


def _intrinsics(d: dict, fallback: dict, size: tuple[int, int], where: str
                ) -> tuple[np.ndarray, int, int, np.ndarray]:
    """(K, w, h, [k1, k2, p1, p2]) of a frame: its own keys first, else the global ones.

    instant-ngp / nerfstudio distortion ``k1 k2 p1 p2`` is OpenCV's (COLMAP OPENCV model);
    ``k3``, ``k4`` or a fisheye flag are refused."""
    get = lambda k: d.get(k, fallback.get(k))  # noqa: E731
    w = get("w") or size[0]
    h = get("h") or size[1]
    if isinstance(w, bool) or isinstance(h, bool) or not isinstance(w, (int, float)) or not isinstance(h, (int, float)) \
            or not (np.isfinite(w) and np.isfinite(h) and w >= 1 and h >= 1 and int(w) == w and int(h) == h):
        raise SceneError(f"{where}: w and h must be positive whole numbers of pixels, got {w!r} x {h!r}")
    check_image_size(int(w), int(h), where)
    for k in ("k3", "k4"):
        if abs(float(get(k) or 0.0)) > 0:
            raise UnsupportedCameraModelError(
                f"{where}: distortion {k} = {get(k)} in transforms.json is not supported (only k1 k2 p1 p2, "
                "COLMAP's OPENCV model); undistort the images first")
    if get("is_fisheye") or str(get("camera_model") or "OPENCV").upper() not in ("OPENCV", "PINHOLE",
                                                                                 "SIMPLE_PINHOLE"):
        raise UnsupportedCameraModelError(f"{where}: fisheye camera model {get('camera_model')!r} is not supported")
    dist = np.array([float(get(k) or 0.0) for k in ("k1", "k2", "p1", "p2")])
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
        fy = float(get("fl_y") if get("fl_y") is not None else fx)
    elif get("camera_angle_x") is not None:
        fx = 0.5 * w / np.tan(0.5 * float(get("camera_angle_x")))
        fy = 0.5 * h / np.tan(0.5 * float(get("camera_angle_y"))) if get("camera_angle_y") is not None else fx
    else:
        raise SceneError(f"{where}: no focal length (fl_x or camera_angle_x)")
    cx = float(get("cx") if get("cx") is not None else w / 2)
    cy = float(get("cy") if get("cy") is not None else h / 2)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), int(w), int(h), dist


def _transforms_json(path: Path) -> Path:
    if path.is_file():
        return path
    for name in ("transforms.json", "transforms_train.json"):
        if (path / name).is_file():
            if name != "transforms.json":
                log.info("%s: using %s (NeRF-synthetic layout; pass the val/test json as --src to use "
                         "those frames)", path, name)
            return path / name
    raise SceneError(f"{path}: no transforms.json or transforms_train.json")


def _load_transforms(path: Path, images_subdir: str | Path | None, skip_missing: bool = False) -> Scene:
    """Cameras from an instant-ngp / nerfstudio / NeRF-synthetic ``transforms*.json``.

    ``transform_matrix`` is camera-to-world in OpenGL axes (x right, y up, z back) and is
    turned into cam_from_world in OpenCV axes. Intrinsics: ``fl_x``/``fl_y``/``cx``/``cy``
    or ``camera_angle_x`` (and ``camera_angle_y``), per frame or global, in pixels of the
    size ``w``/``h`` (default: the image file's), rescaled to the file. Distortion
    ``k1 k2 p1 p2`` is kept as an OPENCV camera model (see :func:`_maybe_undistort`).
    Frames whose image files are missing: error naming the count, or dropped with a
    warning when ``skip_missing``.
    """
    json_path = _transforms_json(path)
    try:
        meta = json.loads(json_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SceneError(f"cannot read {json_path}: {exc}") from exc
    frames = meta.get("frames")
    if not frames:
        raise SceneError(f"{json_path} has no frames")
    base = json_path.parent
    found = [(f, _find_frame_file(base, f.get("file_path", "") if isinstance(f, dict) else None, json_path))
             for f in frames]
    missing = [str(f.get("file_path", "")) for f, p in found if p is None]
    if missing:
        msg = (f"{json_path}: {len(missing)} of {len(frames)} frames name image files that are missing "
               f"under {base} (e.g. {missing[:3]}; also tried .png/.jpg/.jpeg/.exr/.tif)")
        if not skip_missing:
            raise SceneError(msg + "; restore them, or pass --skip-missing to use the "
                             f"{len(frames) - len(missing)} frames that have images")
        log.warning("%s; --skip-missing: using the %d frames that have images", msg, len(frames) - len(missing))
        found = [(f, p) for f, p in found if p is not None]
        if not found:
            raise SceneError(f"{json_path}: no frame has an image file")
    files = [p for _, p in found]
    folders = sorted({str(f.parent) for f in files})
    if images_subdir is None and len(folders) > 1:
        raise SceneError(f"{json_path}: the frames' images lie in {len(folders)} folders ({', '.join(folders[:3])}): "
                         "a scene's images share one folder (their names become file names); move them into "
                         "one, or pass --images-subdir")
    image_dir = _resolve_images(base, images_subdir) if images_subdir is not None else Path(
        _common_dir([f.parent for f in files]))
    cams, models = [], {}
    for (f, file) in found:
        if images_subdir is not None:
            file = image_dir / file.name
            if not file.is_file():
                raise SceneError(f"image {file} named by {json_path} is missing from {image_dir}")
        name = file.relative_to(image_dir.resolve() if images_subdir is None else image_dir).as_posix()
        size = image_size(file)
        K, w, h, dist = _intrinsics(f, meta, size, f"{json_path} frame {name}")
        if "transform_matrix" not in f:
            raise SceneError(f"{json_path}: frame {name} has no transform_matrix")
        c2w = np.asarray(f["transform_matrix"], np.float64)
        if c2w.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(c2w)):
            raise SceneError(f"{json_path}: frame {name}: transform_matrix must be a finite 4x4 matrix")
        cfw = opengl_to_opencv_c2w(c2w)
        if (w, h) != size:
            K = scale_intrinsics(K, size[0] / w, size[1] / h)
        cams.append(Camera(name, size[0], size[1], K, cfw[:3]))
        models[name] = ("OPENCV", np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist]) if np.any(dist != 0) else \
            ("PINHOLE", np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    image_dir = image_dir.resolve() if images_subdir is None else image_dir
    names = sorted(c.name for c in cams)
    if len(set(names)) != len(names):
        raise SceneError(f"{json_path} names the same image twice")
    return Scene(image_dir, names, SparseModel(cams, camera_models=models), "transforms", path)


def _common_dir(dirs: list[Path]) -> Path:
    parts = [d.resolve().parts for d in dirs]
    common = []
    for items in zip(*parts):
        if len(set(items)) != 1:
            break
        common.append(items[0])
    return Path(*common)

