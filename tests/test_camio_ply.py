"""3DGS PLY and plain point PLY round trips, checked with plyfile reading every field."""

from __future__ import annotations

import numpy as np
import pytest

from camio.ply import (
    GaussianCloud, PlyFormatError, read_gaussian_ply, read_points_ply, rgb_to_sh_dc, sh_dc_to_rgb,
    write_gaussian_ply, write_points_ply,
)

plyfile = pytest.importorskip("plyfile")


def _cloud(n=50, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianCloud(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, k, 3)),
                         rng.normal(size=n), rng.normal(size=(n, 3)), rng.normal(size=(n, 4)))


def test_gaussian_roundtrip_every_field_via_plyfile(tmp_path):
    c = _cloud()
    p = write_gaussian_ply(tmp_path / "g.ply", c)
    v = plyfile.PlyData.read(str(p))["vertex"]
    names = [prop.name for prop in v.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert all(prop.val_dtype in ("f4", "<f4", "float32") or str(prop.val_dtype).endswith("f4") for prop in v.properties)
    col = lambda *ks: np.stack([v[k] for k in ks], 1)  # noqa: E731
    np.testing.assert_array_equal(col("x", "y", "z"), c.means)
    np.testing.assert_array_equal(col("nx", "ny", "nz"), 0)
    np.testing.assert_array_equal(col("f_dc_0", "f_dc_1", "f_dc_2"), c.sh_dc)
    rest = col(*[f"f_rest_{i}" for i in range(45)]).reshape(-1, 3, 15)  # channel-major
    np.testing.assert_array_equal(rest.transpose(0, 2, 1), c.sh_rest)
    np.testing.assert_array_equal(v["opacity"], c.opacity_logit)
    np.testing.assert_array_equal(col("scale_0", "scale_1", "scale_2"), c.log_scales)
    np.testing.assert_array_equal(col("rot_0", "rot_1", "rot_2", "rot_3"), c.quats)
    back = read_gaussian_ply(p)
    for f in ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(back, f), getattr(c, f))


def test_lower_degree_padded_and_plyfile_written_file_read(tmp_path):
    c = _cloud(degree=1)
    back = read_gaussian_ply(write_gaussian_ply(tmp_path / "g.ply", c))
    assert back.sh_degree == 3
    np.testing.assert_array_equal(back.sh_rest[:, :3], c.sh_rest)
    np.testing.assert_array_equal(back.sh_rest[:, 3:], 0)
    # a file written by plyfile in another property order with degree 0
    n = 5
    fields = ["rot_0", "rot_1", "rot_2", "rot_3", "x", "y", "z", "scale_0", "scale_1", "scale_2",
              "opacity", "f_dc_0", "f_dc_1", "f_dc_2"]
    arr = np.zeros(n, dtype=[(f, "f4") for f in fields])
    for i, f in enumerate(fields):
        arr[f] = np.arange(n) + i
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "o.ply"))
    g = read_gaussian_ply(tmp_path / "o.ply")
    assert g.sh_degree == 0
    np.testing.assert_array_equal(g.means[:, 0], np.arange(n) + 4)
    np.testing.assert_array_equal(g.quats[:, 0], np.arange(n))


def test_truncated_and_wrong_files(tmp_path):
    p = write_gaussian_ply(tmp_path / "g.ply", _cloud())
    raw = p.read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-10])
    with pytest.raises(PlyFormatError, match="truncated"):
        read_gaussian_ply(tmp_path / "t.ply")
    (tmp_path / "n.ply").write_bytes(b"not a ply")
    with pytest.raises(PlyFormatError, match="not a PLY"):
        read_gaussian_ply(tmp_path / "n.ply")
    write_points_ply(tmp_path / "pts.ply", np.zeros((3, 3)), np.zeros((3, 3), np.uint8))
    with pytest.raises(PlyFormatError, match="missing fields"):
        read_gaussian_ply(tmp_path / "pts.ply")
    arr = np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], text=True).write(str(tmp_path / "a.ply"))
    with pytest.raises(PlyFormatError, match="binary_little_endian"):
        read_points_ply(tmp_path / "a.ply")


def test_points_ply_roundtrip(tmp_path):
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(40, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (40, 3), dtype=np.uint8)
    nrm = rng.normal(size=(40, 3))
    p = write_points_ply(tmp_path / "p.ply", xyz, rgb, nrm)
    v = plyfile.PlyData.read(str(p))["vertex"]
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), xyz)
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), rgb)
    np.testing.assert_allclose(np.stack([v["nx"], v["ny"], v["nz"]], 1), nrm, rtol=1e-6)
    x2, c2 = read_points_ply(p)
    np.testing.assert_array_equal(x2, xyz)
    np.testing.assert_array_equal(c2, rgb)
    raw = p.read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-1])
    with pytest.raises(PlyFormatError, match="truncated"):
        read_points_ply(tmp_path / "t.ply")


def test_sh_helpers_and_seed():
    rgb = np.array([[0.0, 0.5, 1.0]])
    np.testing.assert_allclose(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb, atol=1e-6)
    g = GaussianCloud.from_points(np.zeros((2, 3)), np.full((2, 3), 0.5), [0.1, 0.9], [0.01, 0.02])
    np.testing.assert_allclose(g.opacity, [0.1, 0.9], rtol=1e-6)
    np.testing.assert_allclose(np.exp(g.log_scales[:, 0]), [0.01, 0.02], rtol=1e-6)
    np.testing.assert_array_equal(g.quats, [[1, 0, 0, 0]] * 2)


def test_header_comments_round_trip_and_stay_one_line(tmp_path):
    from camio.ply import ply_comments

    cloud = GaussianCloud.from_points(np.zeros((2, 3)), np.full((2, 3), 0.5), np.full(2, 0.5), np.full(2, 0.1))
    path = write_gaussian_ply(tmp_path / "c.ply", cloud, comments=("iteration 40", "made by a test"))
    raw = path.read_bytes()
    assert ply_comments(raw) == ["iteration 40", "made by a test"]
    assert plyfile.PlyData.read(str(path)).comments == ["iteration 40", "made by a test"]  # standard PLY
    back = read_gaussian_ply(path, raw)  # the bytes given, not the file read again
    np.testing.assert_array_equal(back.means, cloud.means)
    assert ply_comments(b"not a ply") == []
    with pytest.raises(ValueError, match="one line of ASCII"):
        write_gaussian_ply(tmp_path / "d.ply", cloud, comments=("two\nlines",))
    assert not (tmp_path / "d.ply").exists()
