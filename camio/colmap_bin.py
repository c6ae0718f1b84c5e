"""Exact size check of a binary COLMAP model before pycolmap reads it.

pycolmap's binary reader trusts every count it reads: a ``cameras.bin`` cut by a few bytes
is read with a principal point made of whatever follows, and a ``points3D.bin`` cut inside a
track makes it allocate the track length it read (gigabytes). :func:`check_binary_model`
walks ``cameras.bin``, ``images.bin`` and ``points3D.bin`` record by record (COLMAP's
``WriteCamerasBinary`` / ``WriteImagesBinary`` / ``WritePoints3DBinary`` layout,
little-endian) and checks, before anything is allocated, that each record's size (fixed
part, parameter count of its camera model, name up to its NUL, 2D points, track) fits in the
bytes that are left, and that the file ends exactly where its last record does. Nothing is
allocated in proportion to a count read from the file: the walk's memory is bounded by the
file's size (it reads the file once, in memory, as bytes).

Layouts (counts are uint64; ids int32 unless said)::

    cameras.bin   n | n x (camera_id, model_id, width u64, height u64, params f64 x P(model_id))
    images.bin    n | n x (image_id, qvec f64 x 4, tvec f64 x 3, camera_id, name NUL-terminated,
                           m u64, m x (x f64, y f64, point3D_id i64))
    points3D.bin  n | n x (point3D_id u64, xyz f64 x 3, rgb u8 x 3, error f64,
                           t u64, t x (image_id i32, point2D_idx i32))
"""

from __future__ import annotations

import struct
from pathlib import Path

from camio.limits import check_image_size
from runtime.names import check_name

__all__ = ["MODEL_PARAMS", "check_binary_model", "BinaryModelError"]

# COLMAP's camera model ids -> (name, number of parameters) (colmap/sensor/models.h).
MODEL_PARAMS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16), 12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2),
}

MAX_NAME = 4096
"""Longest image name accepted (bytes): a name runs to its NUL, and a damaged file may hold none."""


class BinaryModelError(ValueError):
    """A binary model file whose records do not fit its size (one line naming the file)."""


class _Reader:
    """Walk a bytes buffer; every read is checked against the bytes left."""

    def __init__(self, path: Path):
        self.path = path
        self.buf = path.read_bytes()
        self.pos = 0

    def left(self) -> int:
        return len(self.buf) - self.pos

    def need(self, n: int, what: str) -> None:
        if n > self.left():
            raise BinaryModelError(
                f"{self.path}: {what} needs {n} bytes at offset {self.pos} but only {self.left()} are left: "
                "the file is truncated or damaged; copy or export the model again")

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        self.need(size, what)
        vals = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += size
        return vals

    def skip(self, n: int, what: str) -> None:
        self.need(n, what)
        self.pos += n

    def count(self, min_record: int, what: str) -> int:
        """A uint64 count whose records (each at least ``min_record`` bytes) must fit."""
        n, = self.take("<Q", f"the number of {what}")
        if n * min_record > self.left():
            raise BinaryModelError(
                f"{self.path}: says {n} {what} (at least {n * min_record} bytes) but only {self.left()} bytes "
                "follow: the file is truncated or damaged; copy or export the model again")
        return n

    def end(self) -> None:
        if self.left():
            raise BinaryModelError(f"{self.path}: {self.left()} bytes follow the last record: the file is "
                                   "damaged (or not a COLMAP model); copy or export the model again")


def _cameras(path: Path) -> dict[int, tuple[str, int, int, tuple[float, ...]]]:
    r = _Reader(path)
    out = {}
    for i in range(r.count(4 + 4 + 8 + 8, "cameras")):
        cid, model_id, w, h = r.take("<iiQQ", f"camera record {i + 1}")
        if model_id not in MODEL_PARAMS:
            raise BinaryModelError(f"{path}: camera {cid} has the unknown camera model id {model_id} (record "
                                   f"{i + 1}): the file is damaged or from another program")
        check_image_size(w, h, f"{path}: camera {cid}")
        name, k = MODEL_PARAMS[model_id]
        params = r.take(f"<{k}d", f"camera {cid}'s {k} {name} parameters")
        if cid in out:
            raise BinaryModelError(f"{path}: camera id {cid} appears twice (record {i + 1})")
        out[cid] = (name, w, h, params)
    r.end()
    return out


def _images(path: Path) -> dict[int, str]:
    r = _Reader(path)
    out: dict[int, str] = {}
    names: dict[str, int] = {}
    for i in range(r.count(4 + 56 + 4 + 1 + 8, "images")):
        iid, = r.take("<i", f"image record {i + 1}")
        r.skip(56, f"image {iid}'s pose")
        r.take("<i", f"image {iid}'s camera id")
        end = r.buf.find(b"\0", r.pos, r.pos + MAX_NAME + 1)
        if end < 0:
            raise BinaryModelError(f"{path}: image {iid}'s name has no end within {min(MAX_NAME, r.left())} bytes: "
                                   "the file is truncated or damaged; copy or export the model again")
        name = r.buf[r.pos:end].decode("utf-8", errors="surrogateescape")
        check_name(name, "image name", f"{path} (image {iid})")  # it becomes a path: renders, images
        r.pos = end + 1
        m, = r.take("<Q", f"image {iid}'s number of 2D points")
        r.skip(m * 24, f"image {iid}'s {m} 2D points")
        if iid in out:
            raise BinaryModelError(f"{path}: image id {iid} appears twice (record {i + 1})")
        if name in names:
            raise BinaryModelError(f"{path}: the image name {name!r} appears twice (images {names[name]} and {iid}): "
                                   "each image may appear once")
        out[iid] = name
        names[name] = iid
    r.end()
    return out


def _points(path: Path) -> int:
    r = _Reader(path)
    n = r.count(8 + 24 + 3 + 8 + 8, "points")
    for i in range(n):
        pid, = r.take("<Q", f"point record {i + 1}")
        r.skip(24 + 3 + 8, f"point {pid}'s position, colour and error")
        t, = r.take("<Q", f"point {pid}'s track length")
        r.skip(t * 8, f"point {pid}'s track of {t} entries")
    r.end()
    return n


def check_binary_model(model_dir: str | Path) -> dict[int, tuple[str, int, int, tuple[float, ...]]]:
    """Check that every record of the binary model in ``model_dir`` fits its file exactly
    (module docstring); ids and image names unique.

    Returns:
        camera id -> (model name, width, height, params) as stored (for the value checks).

    Raises:
        BinaryModelError: one line naming the file, the record and the bytes missing.
    """
    model_dir = Path(model_dir)
    cams = _cameras(model_dir / "cameras.bin")
    if (model_dir / "images.bin").is_file():
        _images(model_dir / "images.bin")
    if (model_dir / "points3D.bin").is_file():
        _points(model_dir / "points3D.bin")
    return cams
