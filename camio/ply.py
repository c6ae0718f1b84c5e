"""Gaussian-splat PLY files in the standard 3DGS layout.

Layout (binary little-endian, one float32 property each, in this order), as written by the
original 3DGS code and read by it, gsplat and SuperSplat:

    x y z  nx ny nz  f_dc_0..2  f_rest_0..44  opacity  scale_0..2  rot_0..3

* ``opacity`` is the logit of alpha; ``scale_*`` are log scales (world units);
  ``rot_*`` is the quaternion (w, x, y, z), not necessarily unit length.
* ``f_dc_*`` are the degree-0 SH coefficients of R, G, B (rgb = 0.5 + C0 * f_dc).
* ``f_rest_*`` are stored channel-major: f_rest_{c * (K - 1) + k} is coefficient k + 1 of
  channel c, K = (degree + 1)^2. Degree 3 (45 values) is always written; a lower degree is
  padded with zeros, a higher one refused (never cut silently), and the reader infers K from
  the number of f_rest fields (a count that is no degree's is refused).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_path
from runtime.checks import file_problem

__all__ = ["GaussianCloud", "SH_C0", "rgb_to_sh_dc", "sh_dc_to_rgb", "write_gaussian_ply",
           "read_gaussian_ply", "ply_comments", "ply_vertex_count", "PlyFormatError", "write_points_ply",
           "read_points_ply", "check_seed_cloud",
           "SEED_MAX_ABS_POSITION", "SEED_LOG_SCALE_RANGE", "SH_DEGREE"]

SH_C0 = 0.28209479177387814
#: 3DGS's spherical-harmonics degree: a PLY of this degree has 3 ((SH_DEGREE + 1)^2 - 1)
#: ``f_rest_*`` properties; the Bridge's seed and the trainer use it unless told otherwise
SH_DEGREE = 3


class PlyFormatError(ValueError):
    """A PLY file that is truncated or not in the 3DGS layout."""


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] -> degree-0 SH coefficient, [..., 3] -> [..., 3]."""
    return (np.asarray(rgb, dtype=np.float32) - 0.5) / SH_C0


def sh_dc_to_rgb(dc: np.ndarray) -> np.ndarray:
    """Degree-0 SH coefficient -> RGB (unclamped), [..., 3] -> [..., 3]."""
    return np.asarray(dc, dtype=np.float32) * SH_C0 + 0.5


@dataclass
class GaussianCloud:
    """N Gaussians in world coordinates, stored as the 3DGS PLY stores them.

    Attributes:
        means: [N, 3] float32 centres.
        sh_dc: [N, 3] float32 degree-0 SH coefficients.
        sh_rest: [N, K-1, 3] float32 higher SH coefficients (K = 16 for degree 3).
        opacity_logit: [N] float32 logit(alpha).
        log_scales: [N, 3] float32 log of the per-axis standard deviations.
        quats: [N, 4] float32 rotation quaternions (w, x, y, z).
    """

    means: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    opacity_logit: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.means)
        self.means = np.asarray(self.means, np.float32).reshape(n, 3)
        self.sh_dc = np.asarray(self.sh_dc, np.float32).reshape(n, 3)
        rest = np.asarray(self.sh_rest, np.float32)
        # reshape(0, -1, 3) is ambiguous for an empty cloud: keep the given band count
        self.sh_rest = rest.reshape(n, -1, 3) if n else rest.reshape(0, rest.shape[1] if rest.ndim == 3 else 0, 3)
        self.opacity_logit = np.asarray(self.opacity_logit, np.float32).reshape(n)
        self.log_scales = np.asarray(self.log_scales, np.float32).reshape(n, 3)
        self.quats = np.asarray(self.quats, np.float32).reshape(n, 4)
        k = self.sh_rest.shape[1] + 1
        if int(round(np.sqrt(k))) ** 2 != k:
            raise ValueError(f"sh_rest must hold (d+1)^2 - 1 coefficients, got {k - 1}")

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh_rest.shape[1] + 1))) - 1

    @property
    def opacity(self) -> np.ndarray:
        """[N] alpha in (0, 1)."""
        return 1.0 / (1.0 + np.exp(-self.opacity_logit.astype(np.float64)))

    @staticmethod
    def from_points(
        means: np.ndarray, rgb: np.ndarray, alpha: np.ndarray, scales: np.ndarray, sh_degree: int = SH_DEGREE
    ) -> "GaussianCloud":
        """Seed Gaussians: identity rotations, SH DC from RGB in [0,1], higher bands zero,
        alpha in (0, 1) stored as logit, linear scales [N,3] (or [N]) stored as log."""
        n = len(means)
        alpha = np.clip(np.asarray(alpha, np.float64).reshape(n), 1e-6, 1 - 1e-6)
        scales = np.asarray(scales, np.float64)
        if scales.ndim == 1:
            scales = np.repeat(scales[:, None], 3, axis=1)
        quats = np.zeros((n, 4), np.float32)
        quats[:, 0] = 1.0
        return GaussianCloud(
            means=means,
            sh_dc=rgb_to_sh_dc(rgb),
            sh_rest=np.zeros((n, (sh_degree + 1) ** 2 - 1, 3), np.float32),
            opacity_logit=np.log(alpha / (1 - alpha)),
            log_scales=np.log(scales),
            quats=quats,
        )


_BASE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]


def _field_names(n_rest: int) -> list[str]:
    return (_BASE + [f"f_rest_{i}" for i in range(n_rest)] + ["opacity"]
            + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])


def write_gaussian_ply(path: str | Path, cloud: GaussianCloud, comments: tuple[str, ...] = ()) -> Path:
    """Write ``cloud`` in the 3DGS layout (degree 3, 62 float32 properties), atomically;
    ``comments``: header ``comment`` lines (one line of ASCII each), read by :func:`ply_comments`.
    ValueError naming ``path`` for a cloud of SH degree above 3 (its bands would be lost)."""
    for c in comments:
        if not c.isascii() or "\n" in c or "\r" in c:
            raise ValueError(f"a PLY comment is one line of ASCII, got {c!r}")
    if cloud.sh_degree > SH_DEGREE:
        raise ValueError(f"{path}: SH degree {cloud.sh_degree}: the 3DGS PLY holds degree {SH_DEGREE} at most "
                         f"(its 45 f_rest fields); the higher bands would be lost")
    n = len(cloud)
    rest = np.zeros((n, 15, 3), np.float32)
    k = min(15, cloud.sh_rest.shape[1])
    rest[:, :k] = cloud.sh_rest[:, :k]
    data = np.concatenate(
        [
            cloud.means,
            np.zeros((n, 3), np.float32),
            cloud.sh_dc,
            rest.transpose(0, 2, 1).reshape(n, 45),
            cloud.opacity_logit[:, None],
            cloud.log_scales,
            cloud.quats,
        ],
        axis=1,
    ).astype("<f4")
    names = _field_names(45)
    header = "ply\nformat binary_little_endian 1.0\n"
    header += "".join(f"comment {c}\n" for c in comments)
    header += f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(np.ascontiguousarray(data).tobytes())
    return Path(path)


_PLY_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1",
              "uint8": "u1", "char": "i1", "int8": "i1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4"}


def _header(path: Path, raw: bytes) -> tuple[list[tuple[str, int, list[tuple[str, str, str | None]]]], int]:
    """The elements of a binary little-endian PLY header, in file order, and the body's offset.

    Returns:
        ([(element name, count, [(property name, numpy type, list count type or None)])],
        offset of the first body byte).
    """
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise PlyFormatError(f"{path}: not a PLY file (no 'ply' magic or end_header)")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise PlyFormatError(f"{path}: only binary_little_endian PLY is supported")
    elements: list[tuple[str, int, list]] = []
    for k, line in enumerate(header, 1):
        parts = line.split()
        if not parts or parts[0] in ("ply", "format", "comment", "obj_info"):
            continue
        if parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise PlyFormatError(f"{path}: header line {k}: expected 'element NAME COUNT', got {line!r}")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property" and elements:
            props = elements[-1][2]
            if len(parts) == 5 and parts[1] == "list" and parts[2] in _PLY_TYPES and parts[3] in _PLY_TYPES:
                props.append((parts[4], "<" + _PLY_TYPES[parts[3]], "<" + _PLY_TYPES[parts[2]]))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                props.append((parts[2], "<" + _PLY_TYPES[parts[1]], None))
            else:
                raise PlyFormatError(f"{path}: header line {k}: unsupported property {line!r}")
            if [p[0] for p in props].count(props[-1][0]) > 1:
                raise PlyFormatError(f"{path}: header line {k}: the property {props[-1][0]!r} appears twice in "
                                     f"element {elements[-1][0]!r}")
        else:
            raise PlyFormatError(f"{path}: header line {k}: unexpected {line!r}")
    return elements, end + len(b"end_header\n")


def _skip_element(path: Path, raw: bytes, pos: int, name: str, count: int, props: list) -> int:
    """Offset after ``count`` records of an element that is not read (lists walked, each size
    checked against the bytes left)."""
    if all(p[2] is None for p in props):
        size = count * np.dtype([(p[0], p[1]) for p in props]).itemsize if props else 0
        if size > len(raw) - pos:
            raise PlyFormatError(f"{path}: truncated: element {name!r} needs {size} bytes, {len(raw) - pos} left")
        return pos + size
    for _ in range(count):
        for _, typ, count_type in props:
            if count_type is None:
                pos += np.dtype(typ).itemsize
            else:
                ct = np.dtype(count_type)
                if pos + ct.itemsize > len(raw):
                    raise PlyFormatError(f"{path}: truncated inside element {name!r}")
                k = int(np.frombuffer(raw, ct, 1, pos)[0])
                pos += ct.itemsize + max(k, 0) * np.dtype(typ).itemsize
            if pos > len(raw):
                raise PlyFormatError(f"{path}: truncated inside element {name!r}")
    return pos


def ply_comments(raw: bytes) -> list[str]:
    """The ``comment`` lines of a PLY header (``raw``: the file's bytes, or its start), in
    order, without the word ``comment``; [] when ``raw`` holds no whole header."""
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        return []
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    return [ln[len("comment "):].strip() for ln in lines if ln.startswith("comment ")]


def _read_vertices(path: Path, raw: bytes | None = None) -> np.ndarray:
    """The vertex element of a binary little-endian PLY as a structured array (elements before
    it, such as a camera or a face list, are skipped by their exact sizes). ``raw``: the
    file's bytes when already read (``path`` then only names it in messages)."""
    if raw is None and path.is_dir():
        raise PlyFormatError(file_problem(path, "PLY file", ".ply"))
    raw = path.read_bytes() if raw is None else raw
    elements, pos = _header(path, raw)
    for name, count, props in elements:
        if name == "vertex":
            break
        pos = _skip_element(path, raw, pos, name, count, props)
    else:
        raise PlyFormatError(f"{path}: no vertex element")
    if any(p[2] is not None for p in props):
        raise PlyFormatError(f"{path}: unsupported list property in the vertex element")
    n = count
    dtype = np.dtype([(p[0], p[1]) for p in props])
    body = raw[pos:]
    if len(body) < n * dtype.itemsize:
        raise PlyFormatError(
            f"{path}: truncated: header promises {n} vertices ({n * dtype.itemsize} bytes), "
            f"file holds {len(body)} bytes"
        )
    v = np.frombuffer(body, dtype=dtype, count=n)
    return v


SEED_MAX_ABS_POSITION = 1e8
"""A seed coordinate beyond this is degenerate: float32 keeps ~7 digits, so a scene of unit
size placed there renders as noise (and x1e30 overflows projections)."""

SEED_LOG_SCALE_RANGE = (-30.0, 30.0)
"""Log scales outside this (scales below 1e-13 or above 1e13) are degenerate: exp() gives 0 or
inf in float32, the Gaussian is invisible or covers everything, and its gradient vanishes."""


def check_seed_cloud(cloud: "GaussianCloud", path: str | Path, role: str = "seed") -> list[str]:
    """Check a seed cloud before training (or a trained model before rendering).

    Args:
        cloud: the seed (N Gaussians).
        path: its file, named in every message.
        role: "seed" (a training input) or "model" (a trained model.ply to render).

    Returns:
        Warnings, one sentence each, naming what is degenerate: positions beyond
        :data:`SEED_MAX_ABS_POSITION`, log scales outside :data:`SEED_LOG_SCALE_RANGE`, zero
        quaternions. [] when nothing is.

    Raises:
        PlyFormatError: non-finite values (named by field and count), or no Gaussians.
    """
    n = len(cloud.means)
    if n == 0:
        raise PlyFormatError(f"{path}: the {role} holds no Gaussians")
    fields = {"positions": cloud.means, "colours (sh_dc)": cloud.sh_dc, "SH coefficients": cloud.sh_rest,
              "opacities": cloud.opacity_logit, "log scales": cloud.log_scales, "rotations": cloud.quats}
    bad = [f"{name}: {int((~np.isfinite(a.reshape(n, -1))).any(axis=1).sum())} of {n}"
           for name, a in fields.items() if a.size and not np.all(np.isfinite(a))]
    if bad:
        fix = ("fix or regenerate the seed PLY (e.g. re-run `python -m bridge`)" if role == "seed" else
               "the trained model is damaged; train again (or render an earlier checkpoint's model)")
        raise PlyFormatError(f"{path}: non-finite values in the {role} ({'; '.join(bad)}): {fix}")
    out = []
    far = np.abs(cloud.means).max(axis=1) > SEED_MAX_ABS_POSITION
    if far.any():
        out.append(f"{path}: {int(far.sum())} of {n} positions lie beyond {SEED_MAX_ABS_POSITION:g} "
                   f"(largest {float(np.abs(cloud.means).max()):.3g}): float32 cannot render them; normalise "
                   "the seed (the Bridge does)")
    lo, hi = SEED_LOG_SCALE_RANGE
    odd = ((cloud.log_scales < lo) | (cloud.log_scales > hi)).any(axis=1)
    if odd.any():
        out.append(f"{path}: {int(odd.sum())} of {n} Gaussians have log scales outside [{lo:g}, {hi:g}] "
                   f"(from {float(cloud.log_scales.min()):.3g} to {float(cloud.log_scales.max()):.3g}): "
                   "scales of 0 or inf in float32, so they cannot be trained")
    zq = np.linalg.norm(cloud.quats, axis=1) < 1e-12
    if zq.any():
        out.append(f"{path}: {int(zq.sum())} of {n} Gaussians have a zero rotation quaternion")
    return out


def ply_vertex_count(path: str | Path, header_bytes: int = 1 << 16) -> int:
    """The number of vertices (a model's Gaussians) a PLY's header declares, read from its
    first ``header_bytes`` only (a model of millions of Gaussians is not loaded).

    Raises:
        PlyFormatError: not a binary little-endian PLY, or no ``vertex`` element.
    """
    path = Path(path)
    with open(path, "rb") as f:
        elements, _ = _header(path, f.read(header_bytes))
    counts = [count for name, count, _ in elements if name == "vertex"]
    if not counts:
        raise PlyFormatError(f"{path}: the PLY header declares no vertex element")
    return counts[0]


def read_gaussian_ply(path: str | Path, raw: bytes | None = None) -> GaussianCloud:
    """Read a 3DGS-layout PLY (binary little-endian; any property order; any SH degree).
    ``raw``: the file's bytes when the caller already holds them (the viewer checks exactly the
    bytes it serves); ``path`` then only names the file in messages.

    Raises:
        PlyFormatError: truncated file, wrong format, or missing 3DGS fields.
    """
    path = Path(path)
    v = _read_vertices(path, raw)
    n = len(v)
    dtype = v.dtype
    names = set(dtype.names)
    required = _BASE[:3] + ["f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)] \
        + [f"rot_{i}" for i in range(4)]
    missing = [r for r in required if r not in names]
    if missing:
        raise PlyFormatError(f"{path}: not a 3DGS PLY, missing fields {missing}")
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    k = n_rest // 3 + 1
    if n_rest % 3 or int(round(np.sqrt(k))) ** 2 != k or any(f"f_rest_{i}" not in names for i in range(n_rest)):
        raise PlyFormatError(f"{path}: not a 3DGS PLY: {n_rest} f_rest fields are not f_rest_0.. of 3 * ((d + 1)^2 - 1) "
                             "for an SH degree d (0, 9, 24 or 45 for degree 0..3); write the model in the 3DGS layout")
    col = lambda keys: np.stack([v[k].astype(np.float32) for k in keys], axis=1)  # noqa: E731
    rest = (col([f"f_rest_{i}" for i in range(n_rest)]) if n_rest else np.zeros((n, 0), np.float32))
    rest = rest.reshape(n, 3, n_rest // 3).transpose(0, 2, 1)
    return GaussianCloud(
        means=col(["x", "y", "z"]),
        sh_dc=col(["f_dc_0", "f_dc_1", "f_dc_2"]),
        sh_rest=rest,
        opacity_logit=v["opacity"].astype(np.float32),
        log_scales=col([f"scale_{i}" for i in range(3)]),
        quats=col([f"rot_{i}" for i in range(4)]),
    )


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray,
                     normals: np.ndarray | None = None) -> Path:
    """Write a plain coloured point cloud (binary little-endian PLY), atomically.

    Fields: ``x y z`` float32, optional ``nx ny nz`` float32, ``red green blue`` uchar -- the
    layout MeshLab, Open3D and plyfile read. Not the 3DGS layout.

    Args:
        xyz: [N, 3] points; rgb: [N, 3] uint8 (or float in [0, 1]); normals: [N, 3] or None.
    """
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    n = len(xyz)
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8:
        rgb = np.round(np.clip(rgb.astype(np.float64), 0, 1) * 255).astype(np.uint8)
    rgb = rgb.reshape(n, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(n, dtype=fields)
    v["x"], v["y"], v["z"] = xyz.T
    if normals is not None:
        nrm = np.asarray(normals, np.float32).reshape(n, 3)
        v["nx"], v["ny"], v["nz"] = nrm.T
    v["red"], v["green"], v["blue"] = rgb.T
    types = {"<f4": "float", "u1": "uchar"}
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property {types[t]} {name}\n" for name, t in fields) + "end_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(v.tobytes())
    return Path(path)


def read_points_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read x, y, z and red, green, blue of a binary little-endian PLY point cloud.

    Returns:
        xyz [N, 3] float64, rgb [N, 3] uint8 (grey 128 when the file has no colours).

    Raises:
        PlyFormatError: truncated file, wrong format, or no x/y/z.
    """
    v = _read_vertices(Path(path))
    if not {"x", "y", "z"} <= set(v.dtype.names):
        raise PlyFormatError(f"{path}: no x, y, z vertex properties")
    xyz = np.stack([v[k].astype(np.float64) for k in "xyz"], axis=1)
    if {"red", "green", "blue"} <= set(v.dtype.names):
        rgb = np.stack([v[k] for k in ("red", "green", "blue")], axis=1).astype(np.uint8)
    else:
        rgb = np.full((len(xyz), 3), 128, np.uint8)
    return xyz, rgb
