"""Bridge inputs: a vggt_init ``predictions.npz`` or a COLMAP model, as one flat cloud.

Both readers return a :class:`BridgeInput`: the point cloud flattened to rows (for the
npz, row = flattened pixel index s*H*W + i*W + j, so the pixel stride of the seed code is a
row stride), confidences (None for COLMAP), colours and the cameras at the resolution the
output model is written at. Nothing is filtered here: non-finite rows are dropped and
counted by the Bridge.
"""

from __future__ import annotations

import logging
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from camio.arrays import check_npz
from camio.cameras import Camera
from runtime.checks import file_problem
from runtime.names import check_name_list

__all__ = ["BridgeInput", "load_predictions", "load_colmap", "PREDICTION_KEYS"]

log = logging.getLogger(__name__)

#: keys of predictions.npz the Bridge needs (docs/contracts.md, "vggt_init output")
PREDICTION_KEYS = ("image_names", "cam_from_world", "intrinsics_original", "image_sizes_original",
                   "world_points", "world_points_conf", "colors")


@dataclass
class BridgeInput:
    """A point cloud with cameras, in the input's world frame.

    Attributes:
        source: "vggt" (predictions.npz) or "colmap".
        path: the file or folder read.
        points: [N, 3] float64 world points; may contain NaN/Inf.
        conf: [N] float64 confidences (may contain NaN/Inf), or None (COLMAP).
        colors: [N, 3] uint8 RGB.
        cameras: posed pinhole cameras (cam_from_world, OpenCV axes) with K at their
            width x height, the resolution the output model refers to.
        grid_shape: (S, H, W) of the point map for an npz, None for COLMAP.
        observations: image name -> (xy [K, 2] pixels, rows of ``points`` [K]) for a COLMAP
            model (its tracks; the depth prior's samples), empty otherwise.
    """

    source: str
    path: Path
    points: np.ndarray
    conf: np.ndarray | None
    colors: np.ndarray
    cameras: list[Camera]
    grid_shape: tuple[int, int, int] | None = None
    observations: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, np.float64).reshape(-1, 3)
        n = len(self.points)
        if self.conf is not None:
            self.conf = np.asarray(self.conf, np.float64).reshape(-1)
            if len(self.conf) != n:
                raise ValueError(f"{n} points but {len(self.conf)} confidences")
        self.colors = np.asarray(self.colors).reshape(-1, 3)
        if len(self.colors) != n:
            raise ValueError(f"{n} points but {len(self.colors)} colours")
        if not self.cameras:
            raise ValueError(f"{self.path}: no cameras; the Bridge needs posed cameras to write sparse/0")


def _colors_uint8(colors: np.ndarray, path: Path) -> np.ndarray:
    """uint8 as in the contract; float in [0, 1] is accepted and converted (rounded)."""
    if colors.dtype == np.uint8:
        return colors
    if np.issubdtype(colors.dtype, np.floating):
        c = np.nan_to_num(colors.astype(np.float64), nan=0.0)
        if c.size and c.max() > 1.0 + 1e-6:
            raise ValueError(f"{path}: 'colors' is float with values above 1; the contract is uint8 [S,H,W,3]")
        log.warning("%s: 'colors' is %s, not uint8; converting from [0, 1]", path, colors.dtype)
        return np.clip(np.rint(c * 255.0), 0, 255).astype(np.uint8)
    raise ValueError(f"{path}: 'colors' has dtype {colors.dtype}; the contract is uint8 [S,H,W,3]")


def load_predictions(path: str | Path) -> BridgeInput:
    """Read a vggt_init ``predictions.npz`` (schema: docs/contracts.md).

    The cameras use ``intrinsics_original`` at ``image_sizes_original`` (width, height), so
    the output model refers to the original images, not the network input.

    Returns:
        the cloud with N = S*H*W rows (row = flattened pixel index), in VGGT's frame.

    Raises:
        FileNotFoundError; ValueError (a damaged or truncated file; a missing key, naming the
            schema; a wrong shape).
    """
    path = Path(path)
    problem = file_problem(path, "predictions file")
    if problem:
        raise FileNotFoundError(f"{problem}; run `python -m vggt_init` first")
    try:
        check_npz(path)  # before numpy allocates what a header claims
        with np.load(path, allow_pickle=False) as z:
            files = list(z.files)
            d = {k: z[k] for k in PREDICTION_KEYS if k in files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
        # a truncated or damaged file (e.g. a copy cut short): numpy's messages do not name it
        raise ValueError(f"{path} is damaged or truncated, not a readable predictions.npz "
                         f"({type(exc).__name__}: {exc}); re-run `python -m vggt_init` to write it again") from exc
    missing = [k for k in PREDICTION_KEYS if k not in files]
    if missing:
        raise ValueError(f"{path} lacks keys {missing}; predictions.npz needs {list(PREDICTION_KEYS)} "
                         "(docs/contracts.md)")
    wp = d["world_points"]
    if wp.ndim != 4 or wp.shape[-1] != 3:
        raise ValueError(f"{path}: world_points must be [S,H,W,3], got {wp.shape}")
    S, H, W, _ = wp.shape
    expect = {
        "world_points_conf": (S, H, W), "colors": (S, H, W, 3), "image_names": (S,),
        "intrinsics_original": (S, 3, 3), "image_sizes_original": (S, 2),
    }
    for key, shape in expect.items():
        if d[key].shape != shape:
            raise ValueError(f"{path}: {key} must have shape {list(shape)} to match world_points "
                             f"{list(wp.shape)}, got {list(d[key].shape)}")
    ext = d["cam_from_world"]
    if ext.shape not in ((S, 3, 4), (S, 4, 4)):
        raise ValueError(f"{path}: cam_from_world must be [S,3,4], got {list(ext.shape)}")
    names = check_name_list([str(n) for n in d["image_names"]], path)  # they become file names downstream
    cameras = []
    for i, name in enumerate(names):
        w, h = (int(v) for v in d["image_sizes_original"][i])
        cameras.append(Camera(name, w, h, d["intrinsics_original"][i], ext[i][:3]))
    return BridgeInput(
        source="vggt", path=path, points=wp.reshape(-1, 3), conf=d["world_points_conf"].reshape(-1),
        colors=_colors_uint8(d["colors"], path).reshape(-1, 3), cameras=cameras, grid_shape=(S, H, W),
    )


def load_colmap(model_dir: str | Path, images_dir: str | Path | None = None) -> BridgeInput:
    """Read a COLMAP model (text or binary, via camio.colmap.read_model) as a Bridge input.

    The cameras keep the model's intrinsics and image sizes; the points keep COLMAP's
    colours; there is no confidence. If ``images_dir`` is given, every registered image
    must exist there (a missing one is an error: training would fail later); a size that
    differs from the model's is logged as a warning.
    """
    from camio.colmap import read_model
    from camio.images import image_size

    model = read_model(model_dir)
    if images_dir is not None:
        images_dir = Path(images_dir)
        missing = [c.name for c in model.cameras if not (images_dir / c.name).is_file()]
        if missing:
            raise FileNotFoundError(f"{len(missing)} images of the model are not in {images_dir}: "
                                    f"{missing[:5]}; pass the folder the model was built from")
        for c in model.cameras:
            w, h = image_size(images_dir / c.name)
            if (w, h) != (c.width, c.height):
                log.warning("%s is %dx%d but the model says %dx%d; the model's intrinsics are kept",
                            c.name, w, h, c.width, c.height)
    return BridgeInput(source="colmap", path=Path(model_dir), points=model.points, conf=None,
                       colors=model.colors, cameras=model.cameras, observations=model.observations)
