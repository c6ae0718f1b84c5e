"""The fused bf16 attention kernel (vggt_init.model._attention_kernel) against float64 references.

Checks: accuracy against a float64 SDPA on the same bf16-rounded inputs, compared with ATen's
bf16 SDPA (relative L2 within 1.25x, max abs within 1.5x); ragged query/key blocks (N = 1, 37,
700), several batches and heads, D = 32 / 64 and the refusal of other D; the vectorised exp
within 2 ulp; bitwise independence of the thread count; and that ``fastpath.attention`` uses the
kernel for bf16 and falls back to oneDNN without it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from vggt_init.model import _attention_kernel as ak
from vggt_init.model import fastpath

from _attention_inputs import qkv, rel as _rel

pytestmark = [
    pytest.mark.skipif(not ak.available(), reason=f"bf16 attention kernel unavailable: {ak.build_error()}"),
    pytest.mark.usefixtures("fast_paths_on"),
]


def _qkv_bf16(B, H, N, D, seed=0):
    return tuple(t.bfloat16() for t in qkv(B, H, N, D, seed))


@pytest.mark.parametrize("shape", [(1, 1, 1, 64), (2, 3, 37, 64), (1, 2, 700, 64), (2, 3, 37, 32),
                                   (1, 2, 130, 32)])
def test_kernel_as_accurate_as_sdpa(shape):
    """N = 1 (one padded key block), 37 (one ragged block of rows and keys), 700 (ragged tails)."""
    qb, kb, vb = _qkv_bf16(*shape, seed=sum(shape))
    ref = F.scaled_dot_product_attention(qb.double(), kb.double(), vb.double()).transpose(1, 2)
    with torch.inference_mode():
        ours = ak.attention_bf16(qb, kb, vb)
        aten = F.scaled_dot_product_attention(qb, kb, vb).transpose(1, 2)
    assert ours.shape == (shape[0], shape[2], shape[1], shape[3]) and ours.dtype == torch.bfloat16
    assert ours.is_contiguous()
    e_ours, e_aten = _rel(ours, ref), _rel(aten, ref)
    assert e_ours <= 1.25 * e_aten + 1e-6, (e_ours, e_aten)
    m_ours = float((ours.double() - ref).abs().max())
    m_aten = float((aten.double() - ref).abs().max())
    assert m_ours <= 1.5 * m_aten + 1e-6, (m_ours, m_aten)


def test_kernel_error_is_bf16_rounding_only():
    """Against the float64 result on the same inputs, the kernel's error is at most about one
    bf16 rounding of the output (2^-9 relative), i.e. no structural error from the blocking."""
    qb, kb, vb = _qkv_bf16(1, 2, 300, 64, seed=7)
    ref = F.scaled_dot_product_attention(qb.double(), kb.double(), vb.double()).transpose(1, 2)
    ours = ak.attention_bf16(qb, kb, vb)
    assert _rel(ours, ref) < 2 ** -8


def test_kernel_casts_any_float_dtype_and_strides():
    qb, kb, vb = _qkv_bf16(1, 2, 50, 64, seed=3)
    base = ak.attention_bf16(qb, kb, vb)
    # same values as float32, given as non-contiguous views ([B, N, nh, D] transposed)
    q32, k32, v32 = (t.float().transpose(1, 2).contiguous().transpose(1, 2) for t in (qb, kb, vb))
    assert not q32.is_contiguous()
    assert torch.equal(ak.attention_bf16(q32, k32, v32), base)


@pytest.mark.parametrize("D", [16, 48])
def test_unsupported_head_dim_refused(D):
    qb, kb, vb = _qkv_bf16(1, 2, 10, D)
    assert not ak.supports(D)
    with pytest.raises(ValueError):
        ak.attention_bf16(qb, kb, vb)
    # fastpath falls back to oneDNN for these
    with torch.inference_mode():
        out = fastpath.attention(qb, kb, vb)
    ref = F.scaled_dot_product_attention(qb.double(), kb.double(), vb.double()).transpose(1, 2)
    assert out.dtype == torch.bfloat16 and _rel(out, ref) < 1e-2


def test_exp_within_2_ulp():
    x = torch.cat([torch.linspace(-87.0, 88.0, 400_001),
                   torch.tensor([0.0, -0.0, 1e-8, -1e-8, -0.3466, 0.3466])])
    y = ak.exp_f32(x)
    want = torch.exp(x.double()).float()
    ulps = (y.view(torch.int32).long() - want.view(torch.int32).long()).abs()
    assert int(ulps.max()) <= 2
    # very negative, -inf and NaN arguments give 0 (never NaN); the subnormal range stays close
    edge = torch.tensor([-88.0, -95.0, -103.0, -104.5, -200.0, -1e30, float("-inf"), float("nan")])
    ye = ak.exp_f32(edge)
    assert not torch.isnan(ye).any()
    torch.testing.assert_close(ye.double(), torch.exp(edge.double()).nan_to_num(0.0), rtol=1e-6, atol=2e-45)
    assert torch.equal(ye[4:], torch.zeros(4))


def test_bitwise_independent_of_thread_count():
    qb, kb, vb = _qkv_bf16(2, 3, 333, 64, seed=5)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = ak.attention_bf16(qb, kb, vb)
        torch.set_num_threads(2)
        two = ak.attention_bf16(qb, kb, vb)
        torch.set_num_threads(3)  # more threads than cores: still the same tasks
        three = ak.attention_bf16(qb, kb, vb)
    finally:
        torch.set_num_threads(old)
    assert torch.equal(one, two) and torch.equal(one, three)


def test_fastpath_uses_kernel_for_bf16(monkeypatch):
    qb, kb, vb = _qkv_bf16(1, 2, 70, 64, seed=9)
    calls = []
    real = ak.attention_bf16

    def spy(q, k, v):
        calls.append(q.shape)
        return real(q, k, v)

    monkeypatch.setattr(ak, "attention_bf16", spy)
    with torch.inference_mode():
        out = fastpath.attention(qb, kb, vb)
    assert calls == [qb.shape]
    assert torch.equal(out, real(qb, kb, vb))
    # float32 stays on oneDNN, autograd on ATen
    with torch.inference_mode():
        fastpath.attention(qb.float(), kb.float(), vb.float())
    fastpath.attention(qb, kb, vb)
    assert len(calls) == 1


def test_fastpath_falls_back_without_kernel(monkeypatch):
    qb, kb, vb = _qkv_bf16(1, 2, 70, 64, seed=9)
    monkeypatch.setattr(ak, "available", lambda: False)
    monkeypatch.setattr(ak, "attention_bf16", lambda *a: pytest.fail("kernel used while unavailable"))
    with torch.inference_mode():
        out = fastpath.attention(qb, kb, vb)
        want = fastpath._attention_onednn(qb, kb, vb, torch.bfloat16)
    assert torch.equal(out, want)


def test_env_disables_kernel(tmp_path):
    """VGGT_INIT_NO_KERNEL=1 in a fresh process: available() False, fastpath still works."""
    code = (
        "import torch\n"
        "from vggt_init.model import _attention_kernel as ak, fastpath\n"
        "assert not ak.available() and 'VGGT_INIT_NO_KERNEL' in ak.build_error()\n"
        "q = torch.randn(1, 2, 20, 64).bfloat16()\n"
        "with torch.inference_mode():\n"
        "    out = fastpath.attention(q, q, q)\n"
        "assert out.shape == (1, 20, 2, 64) and out.dtype == torch.bfloat16\n"
        "print('ok')\n"
    )
    env = {**os.environ, "VGGT_INIT_NO_KERNEL": "1", "VGGT_INIT_KERNEL_DIR": str(tmp_path)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr[-2000:]
    assert not list(tmp_path.iterdir())  # nothing was built
