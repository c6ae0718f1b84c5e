"""The depth-prior file (``depth_prior.npz``): the Bridge writes it, the trainer reads it.

One file per seed, beside ``seed.ply`` (docs/contracts.md, "Bridge output"). It holds depth
samples of the training cameras in the seed's normalised frame, as points rather than maps,
so that a dense point map (VGGT, the oracle) and a sparse model's observations (COLMAP,
``posed``) have one layout, and a trainer at any image downsampling finds each sample's
pixel without resampling a map.

Keys (one row per sample unless said):

* ``image_names`` [S] str: the cameras (names as in ``sparse/0``);
* ``image_sizes`` [S, 2] int64: (width, height) of the pixel frame of ``xy`` per camera
  (the camera's image size in ``sparse/0``);
* ``view`` [M] int64: the camera of each sample (index into ``image_names``);
* ``xy`` [M, 2] float32: pixel coordinates in that camera (COLMAP convention: the top-left
  pixel's centre is (0.5, 0.5));
* ``z`` [M] float32: camera z (OpenCV, > 0) in the seed's normalised frame;
* ``weight`` [M] float32 in [0, 1]: the sample's weight (the initialiser's confidence);
* ``source`` [] str: "dense" (a point map per view) or "sparse" (observed model points).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from camio.arrays import check_npz
from runtime.names import check_name_list

__all__ = ["DEPTH_PRIOR_FILE", "DepthSamples", "write_depth_prior", "read_depth_prior"]

DEPTH_PRIOR_FILE = "depth_prior.npz"
_KEYS = ("image_names", "image_sizes", "view", "xy", "z", "weight", "source")


@dataclass
class DepthSamples:
    """The content of a depth-prior file (shapes as in the module docstring)."""

    image_names: list[str]
    image_sizes: np.ndarray
    view: np.ndarray
    xy: np.ndarray
    z: np.ndarray
    weight: np.ndarray
    source: str

    def __post_init__(self) -> None:
        self.image_sizes = np.asarray(self.image_sizes, np.int64).reshape(-1, 2)
        self.view = np.asarray(self.view, np.int64).reshape(-1)
        self.xy = np.asarray(self.xy, np.float32).reshape(-1, 2)
        self.z = np.asarray(self.z, np.float32).reshape(-1)
        self.weight = np.asarray(self.weight, np.float32).reshape(-1)
        m = len(self.view)
        if not len(self.xy) == len(self.z) == len(self.weight) == m:
            raise ValueError(f"depth prior: view, xy, z and weight need one row per sample, got "
                             f"{m}, {len(self.xy)}, {len(self.z)}, {len(self.weight)}")
        if len(self.image_sizes) != len(self.image_names):
            raise ValueError(f"depth prior: {len(self.image_names)} images but {len(self.image_sizes)} sizes")
        if m and (self.view.min() < 0 or self.view.max() >= len(self.image_names)):
            raise ValueError("depth prior: a sample's view index is outside image_names")
        bad = {k: int((~np.isfinite(v)).any(axis=-1).sum() if v.ndim > 1 else (~np.isfinite(v)).sum())
               for k, v in (("xy", self.xy), ("z", self.z), ("weight", self.weight))}
        if any(bad.values()):
            raise ValueError("depth prior: non-finite samples (" + ", ".join(f"{k}: {n}" for k, n in bad.items() if n)
                             + "); write it again with the Bridge")
        if self.source not in ("dense", "sparse"):
            raise ValueError(f"depth prior: source must be 'dense' or 'sparse', got {self.source!r}")


def write_depth_prior(path: str | Path, samples: DepthSamples) -> Path:
    """Write ``samples`` to ``path`` atomically (compressed npz)."""
    from runtime.atomic import save_npz

    return save_npz(path, image_names=np.asarray(samples.image_names, dtype=str), image_sizes=samples.image_sizes,
                    view=samples.view, xy=samples.xy, z=samples.z, weight=samples.weight,
                    source=np.asarray(samples.source))


def read_depth_prior(path: str | Path) -> DepthSamples:
    """Read a depth-prior file; ValueError naming the file when a key is missing or malformed."""
    path = Path(path)
    try:
        check_npz(path)  # before numpy allocates what a header claims
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in _KEYS if k not in data]
            if missing:
                raise ValueError(f"missing keys {missing}")
            names = check_name_list([str(x) for x in data["image_names"]], path)
            return DepthSamples(names, data["image_sizes"], data["view"],
                                data["xy"], data["z"], data["weight"], str(data["source"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: not a readable depth prior (docs/contracts.md, 'Bridge output'): {exc}") from exc
