"""Trained Gaussians in the formats web viewers share: antimatter15 ``.splat`` and Niantic ``.spz``.

The project's own format is the 3DGS PLY (:mod:`camio.ply`); these two are for handing a
model to someone else (``python -m splat_train export``). Both are lossy.

``.splat`` (antimatter15/splat, read by SuperSplat, Spark, gsplat's and nerfstudio's
exporters): no header, N records of 32 bytes, little-endian::

    position float32 x3 | scale float32 x3 (exp of the log scale) |
    colour uint8 x4 (R, G, B = 0.5 + C0 * f_dc, A = sigmoid(opacity); x255, clamped) |
    rotation uint8 x4 (unit quaternion w, x, y, z mapped to q * 128 + 128, clamped)

The records are written most prominent first (descending scale_x * scale_y * scale_z *
alpha, as antimatter15's converter orders them), and the format keeps no higher SH bands
(view-dependent colour is lost). Bytes are rounded to nearest, so a colour or alpha is
within 0.5/255 of the clamped value and a quaternion component within 1/128 (the clamp of
+1 to 255/128 - 1) of the unit quaternion's; positions and scales are float32 exact.

``.spz`` (nianticlabs/spz, gzip of a 16-byte header and quantised sections) is written and
read through the ``gsply`` package (optional: ``pip install gsply``), version 3 (smallest-three
quaternions). SPZ stores the right-up-back (RUB, OpenGL/three.js) frame and a 3DGS PLY is
right-down-front (RDF, OpenCV), so the writer turns the scene by 180 degrees about x
(:func:`rdf_to_rub`: y and z negated, the quaternion's y and z negated, each SH coefficient's
sign flipped by its parity) as Niantic's ``PackOptions{from = RDF}`` does, and the reader
turns it back. Quantisation (the library's): positions 24-bit fixed point with
:data:`SPZ_FRACTIONAL_BITS` fractional bits (error <= 2^-(bits+1); fewer bits when the scene
is larger than 2^(23-bits)), log scales in steps of 1/16 over [-10, 5.9], alpha in steps of
1/255, the SH DC in steps of 1/(0.15 * 255), the higher bands in steps of 1/128 over [-1, 127/128]
(turned into RUB, so a coefficient is kept within 1/256 where |value| <= 127/128, clamped beyond).
"""

from __future__ import annotations

import struct
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_path
from camio.ply import GaussianCloud, read_gaussian_ply, sh_dc_to_rgb, write_gaussian_ply

__all__ = ["EXPORT_FORMATS", "SPLAT_RECORD", "SplatRecords", "SplatFormatError", "SpzUnavailable", "splat_order",
           "write_splat", "read_splat", "rdf_to_rub", "write_spz", "read_spz", "SPZ_FRACTIONAL_BITS", "export_cloud",
           "check_export_out"]

#: the formats ``python -m splat_train export --format`` writes, by file suffix
EXPORT_FORMATS = ("ply", "splat", "spz")

#: one ``.splat`` record (32 bytes)
SPLAT_RECORD = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)),
                         ("rot", "u1", (4,))])

#: SPZ position precision (Niantic's default): 12 fractional bits, ~0.12 mm at metre scale
SPZ_FRACTIONAL_BITS = 12
_SPZ_INT_MAX = (1 << 23) - 1  # signed 24-bit fixed point


class SplatFormatError(ValueError):
    """A ``.splat`` or ``.spz`` file that is not one, or a cloud a format cannot hold."""


class SpzUnavailable(SplatFormatError):
    """``.spz`` asked for without the optional ``gsply`` package (the message says how to install it)."""


@dataclass
class SplatRecords:
    """The contents of a ``.splat`` file, decoded (N records, file order).

    Attributes:
        means: [N, 3] float32 positions (world).
        scales: [N, 3] float32 standard deviations (linear, world units).
        rgba: [N, 4] uint8 colour (R, G, B from the SH DC term) and alpha.
        quats: [N, 4] float64 rotations (w, x, y, z) as stored: (byte - 128) / 128, not
            renormalised.
    """

    means: np.ndarray
    scales: np.ndarray
    rgba: np.ndarray
    quats: np.ndarray


def splat_order(cloud: GaussianCloud) -> np.ndarray:
    """[N] int64 record order of a ``.splat`` file: descending scale product times alpha
    (ties in cloud order)."""
    weight = np.exp(cloud.log_scales.astype(np.float64).sum(axis=1)) * cloud.opacity
    return np.argsort(-weight, kind="stable")


def _unit_quats(cloud: GaussianCloud, fmt: str) -> np.ndarray:
    """[N, 4] float64 the cloud's rotations normalised (w, x, y, z); both formats store unit
    quaternions, so a zero one is refused (SplatFormatError naming ``fmt`` and the count)."""
    q = cloud.quats.astype(np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if len(q) and not (norm > 0).all():
        raise SplatFormatError(f"{int((norm <= 0).sum())} of {len(q)} Gaussians have a zero rotation quaternion; "
                               f"{fmt} stores unit quaternions")
    return q / np.where(norm > 0, norm, 1.0)


def _to_byte(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def write_splat(path: str | Path, cloud: GaussianCloud) -> Path:
    """Write ``cloud`` as an antimatter15 ``.splat`` file (module docstring), atomically.

    Raises:
        SplatFormatError: a zero quaternion (no rotation to store).
    """
    n = len(cloud)
    q = _unit_quats(cloud, ".splat")
    order = splat_order(cloud)
    rec = np.empty(n, SPLAT_RECORD)
    rec["position"] = cloud.means[order]
    rec["scale"] = np.exp(cloud.log_scales[order].astype(np.float64))
    rgb = np.clip(sh_dc_to_rgb(cloud.sh_dc[order]).astype(np.float64), 0.0, 1.0)
    rec["rgba"] = _to_byte(np.concatenate([rgb, cloud.opacity[order, None]], axis=1) * 255.0)
    rec["rot"] = _to_byte(q[order] * 128.0 + 128.0)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(rec.tobytes())
    return Path(path)


def read_splat(path: str | Path, raw: bytes | None = None) -> SplatRecords:
    """Read an antimatter15 ``.splat`` file. ``raw``: the file's bytes when the caller already
    holds them (the viewer checks exactly the bytes it serves); ``path`` then only names the
    file in messages.

    Raises:
        SplatFormatError: empty, a size that is not a whole number of 32-byte records, or a
            position or scale that is not a finite number (scales also > 0).
    """
    if raw is None:
        raw = Path(path).read_bytes()
    if not raw or len(raw) % SPLAT_RECORD.itemsize:
        raise SplatFormatError(f"{path}: not a .splat file: {len(raw)} bytes is not a positive multiple of the "
                               f"{SPLAT_RECORD.itemsize}-byte record")
    rec = np.frombuffer(raw, SPLAT_RECORD)
    bad = ~(np.isfinite(rec["position"]).all(axis=1) & np.isfinite(rec["scale"]).all(axis=1)
            & (rec["scale"] > 0).all(axis=1))
    if bad.any():
        raise SplatFormatError(f"{path}: not a .splat file: {int(bad.sum())} of {len(rec)} records have a position "
                               f"or scale that is not a finite number (scales > 0); first at record "
                               f"{int(np.argmax(bad))}")
    return SplatRecords(means=rec["position"].copy(), scales=rec["scale"].copy(), rgba=rec["rgba"].copy(),
                        quats=(rec["rot"].astype(np.float64) - 128.0) / 128.0)


# Sign of each SH coefficient (3DGS order, bands 1..3) under (x, y, z) -> (x, -y, -z):
# band 1 ~ (y, z, x); band 2 ~ (xy, yz, 3z^2 - r^2, xz, x^2 - y^2);
# band 3 ~ (y(3x^2 - y^2), xyz, y(4z^2 - x^2 - y^2), z(2z^2 - 3x^2 - 3y^2), x(4z^2 - x^2 - y^2),
#           z(x^2 - y^2), x(x^2 - 3y^2))
_SH_FLIP_X_PI = np.array([-1, -1, 1,  -1, 1, 1, -1, 1,  -1, 1, -1, -1, 1, -1, 1], np.float32)


def rdf_to_rub(cloud: GaussianCloud) -> GaussianCloud:
    """The cloud in the other of the RDF (3DGS PLY, OpenCV) and RUB (SPZ, OpenGL) frames: the
    rotation by 180 degrees about x, its own inverse.

    positions (x, y, z) -> (x, -y, -z); quaternions (w, x, y, z) -> (w, x, -y, -z) (the same
    Gaussian seen in the turned frame); SH coefficient k of every channel times its parity
    under the turn (:data:`_SH_FLIP_X_PI`); DC, opacity and scales unchanged.

    Args:
        cloud: N Gaussians, any SH degree up to 3.

    Returns:
        A new cloud (same shapes).
    """
    flip3 = np.array([1.0, -1.0, -1.0], np.float32)
    k = cloud.sh_rest.shape[1]
    return GaussianCloud(means=cloud.means * flip3, sh_dc=cloud.sh_dc.copy(),
                         sh_rest=cloud.sh_rest * _SH_FLIP_X_PI[:k, None],
                         opacity_logit=cloud.opacity_logit.copy(), log_scales=cloud.log_scales.copy(),
                         quats=cloud.quats * np.array([1.0, 1.0, -1.0, -1.0], np.float32))


def _gsply():
    try:
        import gsply
    except ImportError as exc:
        raise SpzUnavailable("writing or reading .spz needs the gsply package: pip install gsply "
                             "(or pip install -e .[share])") from exc
    return gsply


def _fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (at most :data:`SPZ_FRACTIONAL_BITS`) that hold every position."""
    far = float(np.abs(means).max()) if means.size else 0.0
    bits = SPZ_FRACTIONAL_BITS
    while bits > 0 and far * (1 << bits) > _SPZ_INT_MAX:
        bits -= 1
    if far * (1 << bits) > _SPZ_INT_MAX or bits < 1:
        raise SplatFormatError(f"a position {far:.6g} from the origin does not fit .spz's 24-bit fixed point "
                               f"(at most {_SPZ_INT_MAX / 2:.0f} with 1 fractional bit); normalise the scene")
    return bits


def write_spz(path: str | Path, cloud: GaussianCloud) -> Path:
    """Write ``cloud`` (RDF, 3DGS PLY frame) as a Niantic ``.spz`` file (version 3, RUB frame)
    through ``gsply``, atomically. Fractional bits: :func:`_fractional_bits`.

    Raises:
        SplatFormatError: gsply missing, SH degree above 3, positions too far out.
    """
    gsply = _gsply()
    from gsply.gsdata import create_ply_format

    if cloud.sh_degree > 3:
        raise SplatFormatError(f"{path}: SH degree {cloud.sh_degree}: .spz holds degree 3 at most; export --format "
                               "splat (no view-dependent colour) instead")
    rub = rdf_to_rub(cloud)
    n, deg = len(rub), rub.sh_degree
    data = gsply.GSData(means=rub.means, scales=rub.log_scales, quats=_unit_quats(rub, ".spz").astype(np.float32),
                        opacities=rub.opacity_logit, sh0=rub.sh_dc,
                        shN=rub.sh_rest if deg else np.zeros((n, 0, 3), np.float32),
                        _format=create_ply_format(sh_degree=deg))
    bits = _fractional_bits(rub.means)
    with atomic_path(path) as tmp:
        gsply.write_spz(tmp, data, version=3, fractional_bits=bits)
    return Path(path)


def read_spz(path: str | Path, raw: bytes | None = None) -> GaussianCloud:
    """Read a ``.spz`` file (any version ``gsply`` reads) into the RDF (3DGS PLY) frame.
    ``raw``: the file's bytes when the caller already holds them (the viewer checks exactly the
    bytes it serves: gsply reads only files, so these go through a private temporary file);
    ``path`` then only names the file in messages.

    Raises:
        SpzUnavailable: gsply missing.
        SplatFormatError: not an SPZ file.
    """
    gsply = _gsply()
    copy = None
    try:
        if raw is None:
            d = gsply.read_spz(path)
        else:
            with tempfile.TemporaryDirectory(prefix="spz-") as tmp:
                copy = Path(tmp) / "model.spz"
                copy.write_bytes(raw)
                d = gsply.read_spz(copy)
    except (ValueError, OSError, EOFError, zlib.error, struct.error, IndexError) as exc:
        why = str(exc) if copy is None else str(exc).replace(str(copy), str(path))  # name the user's file
        raise SplatFormatError(f"{path}: not a readable .spz file ({why})") from exc
    n = len(d.means)
    rest = np.asarray(d.shN, np.float32) if d.shN is not None and np.asarray(d.shN).size else \
        np.zeros((n, 0, 3), np.float32)
    cloud = GaussianCloud(means=d.means, sh_dc=np.asarray(d.sh0).reshape(n, 3), sh_rest=rest,
                          opacity_logit=d.opacities, log_scales=d.scales, quats=d.quats)
    return rdf_to_rub(cloud)


def check_export_out(out: str | Path, fmt: str) -> str | None:
    """The suffix rule of an export: ``out`` ending in another export format's suffix (an
    ``.spz`` file named ``.splat``: viewers pick the reader by the suffix and fail on it) is
    refused; any other suffix than ``.fmt`` gets a note (returned, for a warning); None when
    the suffix is ``.fmt`` (case-insensitive).

    Raises:
        SplatFormatError: unknown ``fmt``, or a suffix naming another export format.
    """
    if fmt not in EXPORT_FORMATS:
        raise SplatFormatError(f"unknown format {fmt!r}: choose one of {', '.join(EXPORT_FORMATS)}")
    suffix = Path(out).suffix.lower()
    if suffix == f".{fmt}":
        return None
    if suffix[1:] in EXPORT_FORMATS:
        raise SplatFormatError(f"--out {out} ends in {suffix} but --format is {fmt}: viewers read a file by its "
                               f"suffix; name it {Path(out).with_suffix('.' + fmt).name} or pass --format {suffix[1:]}")
    return f"--out {out} does not end in .{fmt}: viewers pick the format by the suffix"


def export_cloud(model: str | Path, fmt: str, out: str | Path) -> tuple[GaussianCloud, Path]:
    """Read a 3DGS PLY ``model`` and write it as ``fmt`` (one of :data:`EXPORT_FORMATS`) to ``out``
    (whose suffix :func:`check_export_out` checks).

    Returns:
        (the cloud read, ``out``).
    """
    check_export_out(out, fmt)
    cloud = read_gaussian_ply(model)
    writer = {"ply": write_gaussian_ply, "splat": write_splat, "spz": write_spz}[fmt]
    return cloud, writer(out, cloud)

