"""The oneDNN inference fast paths (vggt_init.model.fastpath) against float64 references.

They replace ATen's addmm / SDPA for float32 and bf16 CPU inference. The checks:
float32 results within float32 round-off of a float64 reference; bf16 attention as accurate
as ATen's bf16 SDPA; float64, autograd and autocast-to-other-dtypes never take the fast
path (the float64 parity runs must stay on ATen); switching off gives the ATen numbers.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from vggt_init.model import fastpath
from vggt_init.model.layers import Attention, Linear, Mlp, RoPE2D

from _attention_inputs import qkv as _qkv, rel as _rel


pytestmark = pytest.mark.usefixtures("fast_paths_on")


@pytest.mark.parametrize("shape", [(1, 2, 1, 64), (2, 3, 37, 16), (1, 4, 600, 64)])
def test_attention_fp32_matches_float64(shape):
    """Row chunks (ATTENTION_CHUNK = 256) with a ragged last chunk, N = 1, several heads."""
    q, k, v = _qkv(*shape)
    ref = F.scaled_dot_product_attention(q, k, v).transpose(1, 2)
    with torch.inference_mode():
        assert fastpath._compute_dtype(q.float(), k.float(), v.float()) == torch.float32  # fast path taken
        out = fastpath.attention(q.float(), k.float(), v.float())
    assert out.shape == (shape[0], shape[2], shape[1], shape[3]) and out.dtype == torch.float32
    torch.testing.assert_close(out.double(), ref, rtol=1e-5, atol=1e-5)


def test_attention_bf16_as_accurate_as_sdpa():
    q, k, v = _qkv(2, 4, 700, 64, seed=1)
    ref = F.scaled_dot_product_attention(q, k, v).transpose(1, 2)
    qb, kb, vb = (t.bfloat16() for t in (q, k, v))
    with torch.inference_mode():
        ours = fastpath.attention(qb, kb, vb)
        fastpath.set_fast_paths(False)
        aten = fastpath.attention(qb, kb, vb)
    assert ours.dtype == torch.bfloat16
    e_ours, e_aten = _rel(ours, ref), _rel(aten, ref)
    assert e_ours < 1.25 * e_aten + 1e-4, (e_ours, e_aten)


def test_attention_float64_and_autograd_use_aten():
    q, k, v = _qkv(1, 2, 300, 32)
    with torch.inference_mode():
        out = fastpath.attention(q, k, v)
    assert out.dtype == torch.float64
    assert torch.equal(out, F.scaled_dot_product_attention(q, k, v).transpose(1, 2))
    qf = q.float().requires_grad_()
    out = fastpath.attention(qf, k.float(), v.float())
    out.sum().backward()  # the ATen path: differentiable
    assert qf.grad is not None and torch.isfinite(qf.grad).all()


def test_linear_and_fused_gelu_fp32():
    torch.manual_seed(0)
    lin = Linear(48, 80).eval()
    x = torch.randn(3, 17, 48)
    ref = F.linear(x.double(), lin.weight.double(), lin.bias.double())
    with torch.inference_mode():
        y = lin(x)
        h = fastpath.onednn_linear(x, lin.weight, lin.bias, activation="gelu")
        none = fastpath.onednn_linear(x.double(), lin.weight.double(), lin.bias.double())
    assert y.dtype == torch.float32 and none is None
    torch.testing.assert_close(y.double(), ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(h.double(), F.gelu(ref), rtol=1e-5, atol=1e-5)


def test_linear_under_bf16_autocast_computes_in_bf16():
    """Under autocast the fast path must keep autocast's semantics (bf16 out), not run fp32."""
    torch.manual_seed(0)
    lin = Linear(64, 32).eval()
    x = torch.randn(5, 64)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        y = lin(x)
        fastpath.set_fast_paths(False)
        aten = lin(x)
    assert y.dtype == aten.dtype == torch.bfloat16
    torch.testing.assert_close(y.float(), aten.float(), rtol=2e-2, atol=2e-2)


def test_block_modules_agree_with_aten_path():
    """Attention (qk-norm + RoPE) and Mlp modules: fast path == ATen path within fp32 round-off."""
    torch.manual_seed(0)
    attn = Attention(64, 4, qk_norm=True, rope=RoPE2D(100.0)).eval()
    mlp = Mlp(64, 256).eval()
    x = torch.randn(2, 50, 64)
    pos = torch.stack(torch.meshgrid(torch.arange(5), torch.arange(10), indexing="ij"), -1).reshape(1, 50, 2).expand(2, -1, -1)
    with torch.inference_mode():
        fast = (attn(x, pos), mlp(x))
        fastpath.set_fast_paths(False)
        aten = (attn(x, pos), mlp(x))
    for a, b in zip(fast, aten):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_missing_onednn_falls_back_to_aten(monkeypatch, caplog):
    """A torch build whose oneDNN op fails: one warning, then the ATen numbers, path off."""
    def broken(*args, **kwargs):
        raise RuntimeError("no oneDNN in this build")

    monkeypatch.setattr(torch.ops.mkldnn, "_linear_pointwise", broken)
    torch.manual_seed(0)
    lin = Linear(16, 8).eval()
    x = torch.randn(4, 16)
    q, k, v = (t.float() for t in _qkv(1, 2, 10, 16))
    with torch.inference_mode(), caplog.at_level("WARNING", logger="vggt_init.model.fastpath"):
        y = lin(x)
        assert not fastpath.fast_paths_enabled()
        fastpath.set_fast_paths(True)
        a = fastpath.attention(q, k, v)
    assert torch.equal(y, F.linear(x, lin.weight, lin.bias))
    torch.testing.assert_close(a, F.scaled_dot_product_attention(q, k, v).transpose(1, 2))
    assert "oneDNN linear unavailable" in caplog.text and "oneDNN attention unavailable" in caplog.text
