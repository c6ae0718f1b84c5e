"""``python -m splat_train export``: a trained model written as .splat, .spz or .ply and read
back within each format's quantisation (camio.splatfmt)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _cli import ROOT, refused, run
from _view_scene import make_cameras, make_model
from camio.ply import GaussianCloud, read_gaussian_ply, sh_dc_to_rgb, write_gaussian_ply
from camio.splatfmt import (SPZ_FRACTIONAL_BITS, SplatFormatError, rdf_to_rub, read_splat, read_spz,
                            splat_order, write_spz)

# What each format keeps (module docstring of camio.splatfmt): bytes rounded to nearest.
SPLAT_BYTE_TOL = 0.5 / 255 + 1e-6  # colour and alpha after the clamp to [0, 1]
SPLAT_QUAT_TOL = 1 / 128 + 1e-6  # a component of the unit quaternion (+1 clamps to 127/128)
SPZ_POS_TOL = 2.0 ** -(SPZ_FRACTIONAL_BITS + 1) + 1e-6
SPZ_LOG_SCALE_TOL = 1 / 32 + 1e-5
SPZ_ALPHA_TOL = 0.5 / 255 + 1e-6
SPZ_DC_TOL = 0.5 / (0.15 * 255) + 1e-5
SPZ_REST_TOL = 1 / 256 + 1e-6
SPZ_QUAT_TOL = 2e-3  # smallest-three, 9 bits over [-1/sqrt(2), 1/sqrt(2)], the largest recomputed


def _model(tmp_path, n=300, **kw) -> tuple[GaussianCloud, str]:
    """A model whose values lie inside every format's range (SH bands within +-127/128, the
    range .spz keeps in either frame)."""
    c = make_model(n, **kw)
    c.sh_rest = np.clip(c.sh_rest, -0.99, 0.99)
    return c, str(write_gaussian_ply(tmp_path / "model.ply", c))


def _export(fmt: str, model: str, out) -> None:
    p = run(["-m", "splat_train", "export", "--format", fmt, "--out", str(out), model])
    assert p.returncode == 0, p.stdout + p.stderr
    assert out.is_file() and f"as {fmt}" in p.stdout


def test_export_splat_reads_back_within_a_byte(tmp_path):
    c, model = _model(tmp_path)
    out = tmp_path / "share" / "model.splat"
    _export("splat", model, out)
    assert out.stat().st_size == 32 * len(c)
    s = read_splat(out)
    order = splat_order(c)
    weight = np.exp(c.log_scales.astype(np.float64).sum(1)) * c.opacity
    assert np.all(np.diff(weight[order]) <= 0)  # most prominent first
    np.testing.assert_array_equal(s.means, c.means[order])
    np.testing.assert_allclose(s.scales, np.exp(c.log_scales[order].astype(np.float64)), rtol=1e-6)
    rgb = np.clip(sh_dc_to_rgb(c.sh_dc[order]).astype(np.float64), 0, 1)
    assert np.abs(s.rgba[:, :3] / 255.0 - rgb).max() <= SPLAT_BYTE_TOL
    assert np.abs(s.rgba[:, 3] / 255.0 - c.opacity[order]).max() <= SPLAT_BYTE_TOL
    q = c.quats[order] / np.linalg.norm(c.quats[order], axis=1, keepdims=True)
    assert np.abs(s.quats - q).max() <= SPLAT_QUAT_TOL


def test_export_spz_reads_back_within_its_quantisation(tmp_path):
    c, model = _model(tmp_path)
    out = tmp_path / "model.spz"
    _export("spz", model, out)
    assert out.read_bytes()[:2] == b"\x1f\x8b"  # SPZ v3: one gzip stream
    r = read_spz(out)
    assert len(r) == len(c) and r.sh_degree == 3
    assert np.abs(r.means - c.means).max() <= SPZ_POS_TOL
    assert np.abs(r.log_scales - c.log_scales).max() <= SPZ_LOG_SCALE_TOL
    assert np.abs(r.opacity - c.opacity).max() <= SPZ_ALPHA_TOL
    assert np.abs(r.sh_dc - c.sh_dc).max() <= SPZ_DC_TOL
    assert np.abs(r.sh_rest - c.sh_rest).max() <= SPZ_REST_TOL
    q = c.quats / np.linalg.norm(c.quats, axis=1, keepdims=True)
    sign = np.sign(np.sum(r.quats * q, axis=1, keepdims=True))  # q and -q are one rotation
    assert np.abs(r.quats * sign - q).max() <= SPZ_QUAT_TOL


def test_export_spz_stores_the_right_up_back_frame(tmp_path):
    """Niantic's convention: SPZ holds RUB; a 3DGS PLY is RDF. The file itself, read without
    any conversion, has y and z negated (what Niantic's loader turns back for an RDF caller)."""
    import gsply

    c, model = _model(tmp_path, n=50)
    _export("spz", model, tmp_path / "m.spz")
    raw = gsply.read_spz(tmp_path / "m.spz")
    assert np.abs(raw.means - c.means * np.array([1, -1, -1])).max() <= SPZ_POS_TOL
    assert np.abs(raw.means - c.means).max() > 0.1


def test_export_ply_is_the_same_model(tmp_path):
    c, model = _model(tmp_path, n=40)
    _export("ply", model, tmp_path / "copy.ply")
    r = read_gaussian_ply(tmp_path / "copy.ply")
    for a, b in ((r.means, c.means), (r.sh_rest, c.sh_rest), (r.quats, c.quats), (r.log_scales, c.log_scales)):
        np.testing.assert_array_equal(a, b)


def test_spz_far_scene_keeps_fewer_fractional_bits(tmp_path):
    """A scene reaching x = 3,000 does not fit 12 fractional bits (at most 2,048): the writer
    gives up bits, not positions, and says so in the header."""
    import gzip

    c, _ = _model(tmp_path, n=30)
    c.means = c.means * 100.0 + np.array([3000.0, 0.0, 0.0], np.float32)
    far = float(np.abs(c.means).max())
    assert 2048 < far < 4096
    model = str(write_gaussian_ply(tmp_path / "far.ply", c))
    _export("spz", model, tmp_path / "far.spz")
    header = gzip.decompress((tmp_path / "far.spz").read_bytes())[:16]
    assert header[:4] == b"NGSP" and header[13] == 11  # 4,096 * 2^11 = 2^23
    r = read_spz(tmp_path / "far.spz")
    ulp = float(np.spacing(np.float32(far)))  # float32 itself keeps no finer step out there
    assert np.abs(r.means - c.means).max() <= 2.0 ** -12 + ulp


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_spz_keeps_a_lower_sh_degree(tmp_path, degree):
    """A model of SH degree 0..2 (a PLY from another trainer) is written at its own degree."""
    c = make_model(40, sh_degree=degree)
    c.sh_rest = np.clip(c.sh_rest, -0.99, 0.99)
    write_spz(tmp_path / "m.spz", c)
    r = read_spz(tmp_path / "m.spz")
    assert r.sh_degree == degree and r.sh_rest.shape == c.sh_rest.shape
    assert np.abs(r.sh_rest - c.sh_rest).max(initial=0.0) <= SPZ_REST_TOL
    assert np.abs(r.sh_dc - c.sh_dc).max() <= SPZ_DC_TOL


def test_export_refusals(tmp_path):
    c, model = _model(tmp_path, n=20)
    p = run(["-m", "splat_train", "export", "--format", "splat", "--out", str(tmp_path / "x.splat"),
             str(tmp_path / "nothing.ply")])
    refused(p, "nothing.ply")
    assert not (tmp_path / "x.splat").exists()
    c.means[0] = 1e9  # beyond .spz's 24-bit fixed point at any precision
    far = str(write_gaussian_ply(tmp_path / "far.ply", c))
    p = run(["-m", "splat_train", "export", "--format", "spz", "--out", str(tmp_path / "far.spz"), far])
    refused(p, "24-bit", "normalise")
    assert not (tmp_path / "far.spz").exists()
    c.means[0] = 0.0
    c.quats[3] = 0.0  # no rotation to store
    zero = str(write_gaussian_ply(tmp_path / "zero.ply", c))
    for fmt in ("splat", "spz"):
        p = run(["-m", "splat_train", "export", "--format", fmt, "--out", str(tmp_path / f"zero.{fmt}"), zero])
        refused(p, "1 of 20", "zero rotation quaternion", f".{fmt}")
        assert not (tmp_path / f"zero.{fmt}").exists()
    (tmp_path / "mine.splat").write_bytes(b"a user's file")
    p = run(["-m", "splat_train", "export", "--format", "splat", "--out", str(tmp_path / "mine.splat"), model])
    refused(p, "mine.splat")
    assert (tmp_path / "mine.splat").read_bytes() == b"a user's file"


def test_export_spz_without_gsply_names_the_package(tmp_path):
    """Without gsply, .spz is one line naming the package; .splat still works."""
    import os
    import subprocess
    import sys

    _, model = _model(tmp_path, n=10)
    block = tmp_path / "block"
    (block / "gsply").mkdir(parents=True)
    (block / "gsply" / "__init__.py").write_text("raise ImportError('blocked for the test', name='gsply')\n")
    env = {**os.environ, "PYTHONPATH": f"{block}{os.pathsep}{ROOT}"}
    args = [sys.executable, "-m", "splat_train", "export", "--out"]
    p = subprocess.run(args + [str(tmp_path / "m.spz"), "--format", "spz", model], capture_output=True,
                       text=True, cwd=ROOT, env=env, timeout=120)
    refused(p, "gsply", "pip install")
    assert not (tmp_path / "m.spz").exists()
    p = subprocess.run(args + [str(tmp_path / "m.splat"), "--format", "splat", model], capture_output=True,
                       text=True, cwd=ROOT, env=env, timeout=120)
    assert p.returncode == 0, p.stderr


def test_read_splat_refuses_a_torn_file(tmp_path):
    (tmp_path / "t.splat").write_bytes(bytes(32 * 3 + 5))
    with pytest.raises(SplatFormatError, match="32-byte"):
        read_splat(tmp_path / "t.splat")


def test_rdf_to_rub_is_the_same_scene_turned():
    """The frame change renders the same image from the turned camera (SH bands included), and
    applied twice is the identity."""
    from splat_train import rasterize

    c = make_model(120, seed=3)
    turned = rdf_to_rub(c)
    back = rdf_to_rub(turned)
    for a, b in ((back.means, c.means), (back.quats, c.quats), (back.sh_rest, c.sh_rest)):
        np.testing.assert_array_equal(a, b)
    cam = make_cameras(64, 48, n=3)[1]
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # world RUB -> RDF (its own inverse)

    def render(cloud, cam_from_world):
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64).float()  # noqa: E731
        sh = torch.cat([t(cloud.sh_dc)[:, None], t(cloud.sh_rest)], 1)
        m = np.eye(4)
        m[:3] = cam_from_world[:3]
        return rasterize(t(cloud.means), t(cloud.quats), torch.exp(t(cloud.log_scales)),
                         torch.sigmoid(t(cloud.opacity_logit)), sh, t(m), t(cam.K), cam.width, cam.height,
                         sh_degree=3, backend="torch")["rgb"].numpy()

    m = np.eye(4)
    m[:3] = cam.cam_from_world
    a, b = render(c, m), render(turned, m @ flip)
    assert a.max() > 0.2
    np.testing.assert_allclose(b, a, atol=2e-5)
