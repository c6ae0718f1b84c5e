"""VGGT memory at many frames: token-chunked blocks, query-chunked attention, the memory probe.

The chunked paths switch on above thresholds read at call time (``layers.TOKEN_CHUNK``,
``fastpath.QUERY_CHUNK_MIN_ROWS``); these tests set them small so the fixture model and small
tensors take them, and check the numbers against one pass and the official fixtures.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from vggt_init.model import VGGT, VGGTConfig, fastpath, layers
from vggt_init.model.heads import take_tokens
from vggt_init.model.layers import Block, RoPE2D

from _attention_inputs import qkv as _qkv, rel as _rel

safetensors_torch = pytest.importorskip("safetensors.torch")

FIX = Path(__file__).parent / "data" / "vggt" / "shared"
OUTPUTS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")


def _fixture_model(dtype: torch.dtype) -> VGGT:
    cfg = VGGTConfig.from_fixture_config(json.loads((FIX / "config.json").read_text()))
    model = VGGT(cfg)
    sd = safetensors_torch.load_file(str(FIX / "weights.safetensors"))
    model.load_state_dict({k: v for k, v in sd.items() if not k.startswith("track_head.")}, strict=True)
    return model.to(dtype).eval()


def _block(seed: int = 0) -> Block:
    torch.manual_seed(seed)
    blk = Block(32, 2, qk_norm=True, rope=RoPE2D(100.0)).eval()
    with torch.no_grad():
        for p in blk.parameters():
            p.add_(torch.randn_like(p) * 0.1)  # LayerNorm / LayerScale away from 1 / 0
    return blk


def _pos(B: int, N: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return torch.randint(0, 9, (B, N, 2), generator=g)


@pytest.mark.parametrize("mode", ["float64", "float32", "bf16"])
@pytest.mark.parametrize("shape,chunk", [((3, 40), 50), ((1, 120), 32), ((2, 45), 20)],
                         ids=["whole-sequences", "token-chunks", "token-chunks-batched"])
def test_block_chunked_equals_one_pass(monkeypatch, mode, shape, chunk):
    """Both chunked forms (groups of sequences; token-wise parts in ragged token chunks with
    attention over all tokens) give the one-pass numbers: float64 to round-off, float32 ~1e-6,
    bf16 autocast within bf16 rounding."""
    B, N = shape
    dtype = torch.float32 if mode == "bf16" else getattr(torch, mode)
    blk = _block().to(dtype)
    x = torch.randn(B, N, 32, generator=torch.Generator().manual_seed(1)).to(dtype)
    pos = _pos(B, N)
    ctx = (lambda: torch.autocast("cpu", dtype=torch.bfloat16)) if mode == "bf16" else torch.inference_mode
    with torch.inference_mode(), ctx():
        ref = blk(x, pos)
        monkeypatch.setattr(layers, "TOKEN_CHUNK", chunk)
        calls = []
        for name in ("_forward_sequences", "_forward_tokens"):
            orig = getattr(Block, name)
            monkeypatch.setattr(Block, name, lambda self, *a, _o=orig, _n=name: (calls.append(_n), _o(self, *a))[1])
        out = blk(x, pos)
    assert calls == (["_forward_sequences"] if N <= chunk else ["_forward_tokens"])
    assert out.dtype == ref.dtype and out.shape == ref.shape
    if mode == "float64":
        torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    elif mode == "float32":
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    else:
        assert _rel(out, ref.double()) < 1e-2


def test_block_not_chunked_under_autograd(monkeypatch):
    blk = _block()
    x = torch.randn(1, 60, 32, requires_grad=True)
    monkeypatch.setattr(layers, "TOKEN_CHUNK", 16)
    monkeypatch.setattr(Block, "_forward_tokens", lambda *a: pytest.fail("chunked under autograd"))
    blk(x, _pos(1, 60)).sum().backward()
    assert x.grad is not None


def test_token_chunks_lower_the_block_peak(monkeypatch):
    """Live tensor bytes of one long-sequence block beyond its input, R = one [N, C] float32:
    one pass ~10 R (LayerNorm, qkv, q/k copies, MLP hidden and GELU at 4 C); token chunks ~4 R
    (q, k, v, attention output, then the residual) plus a chunk. Under the probe the same."""
    from benchmarks.vggt_frames import LiveTensorBytes

    torch.manual_seed(0)
    blk = Block(64, 4, qk_norm=True, rope=RoPE2D(100.0)).eval()
    N = 4096
    x, pos = torch.randn(1, N, 64), _pos(1, N)
    R = N * 64 * 4
    peaks = {}
    previous = fastpath.set_fast_paths(False)  # the ATen attention, as on CUDA
    try:
        for chunk, probe in ((1 << 30, False), (256, False), (256, True)):
            monkeypatch.setattr(layers, "TOKEN_CHUNK", chunk)
            with torch.inference_mode(), LiveTensorBytes([x, pos, *blk.parameters()]) as t:
                if probe:
                    with fastpath.memory_probe():
                        blk(x, pos)
                else:
                    blk(x, pos)
            peaks[chunk, probe] = t.peak / R
    finally:
        fastpath.set_fast_paths(previous)
    assert peaks[1 << 30, False] > 9
    assert peaks[256, False] < 4.5
    assert peaks[256, True] == peaks[256, False]


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_fixture_parity_with_chunked_blocks(monkeypatch, dtype, tol):
    """The official fixture outputs with every block chunked (frame blocks by whole frames,
    global blocks in ragged token chunks), as close as the one-pass parity tests require, and
    equal to our one-pass run to round-off."""
    model = _fixture_model(dtype)
    inputs = safetensors_torch.load_file(str(FIX / "inputs.safetensors"))
    expected = safetensors_torch.load_file(str(FIX / ("expected.safetensors" if dtype == torch.float64
                                                      else "expected_fp32.safetensors")))
    x = inputs["images"].to(dtype)
    with torch.inference_mode():
        ref = model(x)
        monkeypatch.setattr(layers, "TOKEN_CHUNK", 20)  # 17 tokens a frame: frames 1 by 1; global 51 in 20s
        out = model(x)
    for k in OUTPUTS:
        torch.testing.assert_close(out[k].double(), expected[k].double(), rtol=tol, atol=tol, msg=lambda m: f"{k}: {m}")
        torch.testing.assert_close(out[k], ref[k], rtol=1e-5 if dtype == torch.float32 else 1e-12,
                                   atol=1e-5 if dtype == torch.float32 else 1e-12)


def test_bf16_trunk_chunked_agrees_with_one_pass(monkeypatch):
    model = _fixture_model(torch.float32).cast_trunk_weights(torch.bfloat16)
    x = safetensors_torch.load_file(str(FIX / "inputs.safetensors"))["images"]
    with torch.inference_mode():
        ref = model(x)
        monkeypatch.setattr(layers, "TOKEN_CHUNK", 20)
        out = model(x)
    for k in OUTPUTS:
        assert out[k].dtype == torch.float32
        assert _rel(out[k], ref[k].double()) < 1e-2, k


def test_aggregator_halves_are_the_concatenation():
    """concat=False (what the model's heads read) holds the two halves of concat=True's output;
    take_tokens joins and casts a slice as the heads need it."""
    model = _fixture_model(torch.float64)
    x = safetensors_torch.load_file(str(FIX / "inputs.safetensors"))["images"].double()[None]
    with torch.inference_mode():
        cat = model.aggregator(x, keep=model.layers_needed)
        halves = model.aggregator(x, keep=model.layers_needed, concat=False)
    assert set(cat) == set(halves)
    for i, (f, g) in halves.items():
        assert torch.equal(torch.cat((f, g), dim=-1), cat[i])
        part = take_tokens((f, g), slice(1, 3), slice(5, None), torch.float32)
        assert part.dtype == torch.float32 and torch.equal(part, cat[i][:, 1:3, 5:].float())
        assert torch.equal(take_tokens((f, g), slice(None), 0, torch.float64), cat[i][:, :, 0])
        assert torch.equal(take_tokens(cat[i], slice(None), 0, torch.float64), cat[i][:, :, 0])


@pytest.mark.parametrize("chunk", [None, 2])
def test_forward_equals_heads_on_the_kept_layers(chunk):
    """The model hands each kept layer to its heads as soon as it exists (camera token, DPT
    projections) instead of keeping it: the outputs are those of the heads run on the kept
    layers afterwards, bit for bit, and the timings still name the trunk and each head."""
    model = _fixture_model(torch.float32)
    x = safetensors_torch.load_file(str(FIX / "inputs.safetensors"))["images"][None]
    H, W = x.shape[-2:]
    psi = model.aggregator.patch_start_idx
    timings = {}
    with torch.inference_mode():
        out = model(x, frames_chunk_size=chunk, timings=timings)
        tokens = model.aggregator(x, keep=model.layers_needed)
        poses = model.camera_head(tokens[model.config.camera_head.token_layer % model.config.aggregator.depth])
        depth, depth_conf = model.depth_head(tokens, (H, W), psi, chunk)
        points, points_conf = model.point_head(tokens, (H, W), psi, chunk)
    assert torch.equal(out["pose_enc"], poses[-1])
    for got, want in ((out["depth"], depth), (out["depth_conf"], depth_conf), (out["world_points"], points),
                      (out["world_points_conf"], points_conf)):
        assert torch.equal(got, want)
    assert set(timings) == {"aggregator", "camera_head", "depth_head", "point_head"}
    assert all(v >= 0 for v in timings.values())


def test_dpt_projected_input_equals_tokens_and_checks_chunks():
    from vggt_init.model.heads import Projected

    model = _fixture_model(torch.float64)
    x = safetensors_torch.load_file(str(FIX / "inputs.safetensors"))["images"].double()[None]
    H, W = x.shape[-2:]
    psi = model.aggregator.patch_start_idx
    head = model.point_head
    with torch.inference_mode():
        tokens = model.aggregator(x, keep=model.layers_needed, concat=False)
        ref = head(tokens, (H, W), psi, 2)
        proj = Projected(1, x.shape[1], 2, [head.project_all(k, tokens[layer], psi, (H, W), 2)
                                            for k, layer in enumerate(head.layers)])
        got = head(None, (H, W), psi, 2, projected=proj)
        assert all(m is None for maps in proj.maps for m in maps)  # consumed chunk by chunk
        with pytest.raises(ValueError, match="frames_chunk_size"):
            head(None, (H, W), psi, 1, projected=Projected(1, x.shape[1], 2, [[None, None]] * 4))
    assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1])


def test_aggregator_hands_kept_layers_over_once():
    model = _fixture_model(torch.float64)
    x = safetensors_torch.load_file(str(FIX / "inputs.safetensors"))["images"].double()[None]
    seen = []
    with torch.inference_mode():
        ref = model.aggregator(x, keep=[1, 3])
        kept = model.aggregator(x, keep=[1, 3], on_layer=lambda i, f, g: seen.append((i, torch.cat((f, g), -1))))
    assert kept == {} and [i for i, _ in seen] == [1, 3]
    for i, t in seen:
        assert torch.equal(t, ref[i])


# ---------------------------------------------------------------------- query-chunked attention
@pytest.mark.parametrize("rows", [1, 7, 64, 1000])
def test_query_chunked_attention_float32(rows):
    q, k, v = _qkv(2, 3, 150, 16, seed=2)  # float64
    ref = F.scaled_dot_product_attention(q, k, v).transpose(1, 2)
    one = F.scaled_dot_product_attention(q.float(), k.float(), v.float()).transpose(1, 2)
    out = fastpath.attention_query_chunked(q.float(), k.float(), v.float(), rows)
    assert out.shape == (2, 150, 3, 16) and out.dtype == torch.float32 and out.is_contiguous()
    assert _rel(out, one.double()) < 1e-6
    assert _rel(out, ref) < 1e-6


def test_query_chunked_attention_bf16_and_float64():
    q, k, v = _qkv(1, 4, 200, 32, seed=4)
    ref = F.scaled_dot_product_attention(q, k, v).transpose(1, 2)
    assert torch.allclose(fastpath.attention_query_chunked(q, k, v, 33), ref, rtol=1e-12, atol=1e-12)
    qb, kb, vb = (t.bfloat16() for t in (q, k, v))
    out = fastpath.attention_query_chunked(qb, kb, vb, 33)
    one = F.scaled_dot_product_attention(qb, kb, vb).transpose(1, 2)
    assert out.dtype == torch.bfloat16
    assert _rel(out, ref) < 1e-2 and _rel(out, one.double()) < 1e-2
    with torch.autocast("cpu", dtype=torch.bfloat16):  # float32 inputs under autocast: bf16 out
        assert fastpath.attention_query_chunked(q.float(), k.float(), v.float(), 50).dtype == torch.bfloat16
    with pytest.raises(ValueError):
        fastpath.attention_query_chunked(q, k, v, 0)


def test_attention_takes_query_chunks_off_the_cpu_beyond_threshold(monkeypatch):
    """Off the CPU (a meta tensor stands in for CUDA here), above QUERY_CHUNK_MIN_ROWS rows."""
    seen = []
    real = fastpath.attention_query_chunked
    monkeypatch.setattr(fastpath, "attention_query_chunked", lambda q, k, v, rows: (seen.append(rows), real(q, k, v, rows))[1])
    q = torch.empty(1, 2, 40, 8, device="meta")
    assert fastpath.attention(q, q, q).shape == (1, 40, 2, 8) and seen == []  # 80 rows < 2**22
    monkeypatch.setattr(fastpath, "QUERY_CHUNK_MIN_ROWS", 64)
    monkeypatch.setattr(fastpath, "QUERY_CHUNK_ROWS", 16)
    assert fastpath.attention(q, q, q).shape == (1, 40, 2, 8) and seen == [16]
    qc = torch.randn(1, 2, 40, 8)
    fastpath.attention(qc, qc, qc)  # CPU tensors never take it
    assert seen == [16]


# ---------------------------------------------------------------------- memory probe
def test_memory_probe_skips_attention_and_keeps_shapes(monkeypatch):
    """Inside memory_probe no attention is computed (SDPA would raise), the forward runs and
    its outputs have the real ones' shapes and dtypes; the switch is restored after, also on error."""
    model = _fixture_model(torch.float32).cast_trunk_weights(torch.bfloat16)
    x = safetensors_torch.load_file(str(FIX / "inputs.safetensors"))["images"]
    previous = fastpath.set_fast_paths(False)  # the ATen (SDPA) path, what CUDA takes
    try:
        with torch.inference_mode():
            real = model(x)
            with monkeypatch.context() as m:
                m.setattr(fastpath.F, "scaled_dot_product_attention", lambda *a, **k: pytest.fail("attention computed"))
                with fastpath.memory_probe():
                    assert fastpath.probing()
                    fake = model(x)
            fastpath.set_fast_paths(True)
            with fastpath.memory_probe():  # the CPU fast paths' stand-in
                fast = model(x)
    finally:
        fastpath.set_fast_paths(previous)
    assert not fastpath.probing()
    for out in (fake, fast):
        assert {k: (v.shape, v.dtype) for k, v in out.items() if torch.is_tensor(v)} == \
               {k: (v.shape, v.dtype) for k, v in real.items() if torch.is_tensor(v)}
    with pytest.raises(RuntimeError):
        with fastpath.memory_probe():
            raise RuntimeError("boom")
    assert not fastpath.probing()


def test_memory_probe_output_dtype_and_allocation():
    q, k, v = (t.float() for t in _qkv(1, 2, 30, 8))
    with fastpath.memory_probe(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = fastpath._sdpa(q, k, v)
    assert out.shape == (1, 2, 30, 8) and out.dtype == torch.bfloat16
    assert torch.equal(out, v.bfloat16())


def test_memory_probe_not_reachable_from_vggt_init():
    """Only the benchmark enters the probe: no vggt_init module but fastpath names it."""
    root = Path(__file__).resolve().parents[1] / "vggt_init"
    users = [p.relative_to(root).as_posix() for p in root.rglob("*.py") if "memory_probe" in p.read_text()]
    assert users == ["model/fastpath.py"]
