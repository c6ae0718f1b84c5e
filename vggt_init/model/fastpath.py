"""CPU inference fast paths through oneDNN: Linear (+ fused GELU) and attention.

Why: ATen's float32 ``addmm`` and ``scaled_dot_product_attention`` call MKL's sgemm, which
takes a slow code path on the AMD EPYC (Zen 5) machines this project runs on. Measured with
2 threads on such a machine:

- Linear 4122x1024 @ 1024x3072: ~150 GFLOP/s through ``F.linear``, ~290 through oneDNN
  (``torch.ops.mkldnn._linear_pointwise``); fc1 + exact GELU fused there: 0.13 s vs 0.27 s.
- Attention, 16 heads of 64 over 4122 tokens: SDPA 0.48 s (fp32) / 0.46 s (bf16); the
  row-chunked oneDNN form below 0.31 s (fp32) / 0.29 s (bf16).
- bf16 attention on CPUs with AVX512-BF16 goes to the fused flash-style C++ kernel in
  ``_attention_kernel`` (vdpbf16ps, online softmax, no [N, N] scores): medians of 7 interleaved
  runs, 0.145 s vs 0.371 s oneDNN / 0.487 s SDPA for 16 x 4122 tokens, 0.061 s vs 0.150 / 0.159 s
  for the frame attention 3 x 16 x 1374, and 2.28 s vs 7.70 / 7.40 s for 16 x 16488 (12 frames).

Numerics: the float32 results differ from ATen's only by summation order (~1e-6 relative;
the fixtures' float32 tolerance is 1e-4). In bf16 (autocast) the scores q k^T are computed
in float32 from the (bf16-valued) q, k, softmax in float32, then P and V in bf16 with
float32 accumulation: the precision of SDPA's bf16 kernel (measured rms error against a
float64 reference 0.00096 vs SDPA's 0.00094). The fused kernel has the same precision (it
rounds q, k to bf16 where they come as float32, as autocast's SDPA does). float64, autograd,
other autocast dtypes and non-CPU tensors always take the ATen path, so the float64 parity runs
never use this module. ``VGGT_INIT_ONEDNN=0`` (environment) or ``set_fast_paths(False)``
switches it all off; ``VGGT_INIT_NO_KERNEL=1`` only the fused kernel.

Off the CPU, attention is ``F.scaled_dot_product_attention``. Global attention at many frames
(N = frames x 1041 tokens at 518x392, ~1e6 at 1,000 frames) goes through
:func:`attention_query_chunked` once B x heads x N exceeds :data:`QUERY_CHUNK_MIN_ROWS`: the
queries in chunks of :data:`QUERY_CHUNK_ROWS` rows, each chunk against the full K and V, written
into one [B, N, nh, D] output. Why: SDPA's fused backends (flash, memory-efficient) keep no
scores, but the math backend (float64, shapes or dtypes the fused kernels refuse) materialises
[B, nh, N, N] scores, impossible at N ~ 1e6; with query chunks it holds at most
B x nh x QUERY_CHUNK_ROWS x N of them. The output also lands token-major directly, instead of
SDPA's [B, nh, N, D] buffer and a transposed copy of it. Each query row is computed from the
same full K, V as in one pass (equal within the backend's rounding; flash's rows are independent
of the other rows). Both thresholds are read at call time (tests set them small).

:func:`memory_probe` is for memory searches only (``benchmarks/vggt_frames.py``): inside it, the
attention returns a tensor of the real output's shape, dtype and allocation without computing it
(MEANINGLESS values), so a forward at S frames allocates what the real one does, without the
O(N^2) arithmetic. Nothing in the ``vggt_init`` command line enters it.
"""

from __future__ import annotations

import contextlib
import logging
import os

import torch
import torch.nn.functional as F

from vggt_init.model import _attention_kernel

__all__ = ["set_fast_paths", "fast_paths_enabled", "onednn_linear", "attention", "ATTENTION_CHUNK",
           "attention_query_chunked", "memory_probe", "probing", "QUERY_CHUNK_MIN_ROWS", "QUERY_CHUNK_ROWS"]

log = logging.getLogger(__name__)

_STATE = {"enabled": os.environ.get("VGGT_INIT_ONEDNN", "1") != "0", "probe": False}
ATTENTION_CHUNK = 256  # query rows per oneDNN score block: 256 x N float32 scores at a time
QUERY_CHUNK_MIN_ROWS = 1 << 22  # off the CPU, B x heads x N above this: queries in chunks (~250 frames, 16 heads)
QUERY_CHUNK_ROWS = 1 << 15  # query rows per chunk of attention_query_chunked
_FAST_DTYPES = (torch.float32, torch.bfloat16)


def set_fast_paths(enabled: bool) -> bool:
    """Switch the oneDNN paths on or off; returns the previous setting."""
    previous = _STATE["enabled"]
    _STATE["enabled"] = bool(enabled)
    return previous


def fast_paths_enabled() -> bool:
    return _STATE["enabled"]


def _compute_dtype(*tensors: torch.Tensor | None) -> torch.dtype | None:
    """The dtype a fast path computes in for these tensors, or None to use ATen.

    Under CPU autocast to bf16: bf16. Otherwise the tensors' common dtype if it is float32
    or bf16. None when switched off, under autograd, or off the CPU.
    """
    if not _STATE["enabled"] or torch.is_grad_enabled():
        return None
    ts = [t for t in tensors if t is not None]
    if any(t.device.type != "cpu" for t in ts):
        return None
    if torch.is_autocast_enabled("cpu"):
        dt = torch.get_autocast_dtype("cpu")
        return dt if dt == torch.bfloat16 else None
    dt = ts[0].dtype
    return dt if dt in _FAST_DTYPES and all(t.dtype == dt for t in ts) else None


def _disable(what: str, exc: Exception) -> None:
    log.warning("oneDNN %s unavailable (%s); using ATen from now on", what, exc)
    _STATE["enabled"] = False


def onednn_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None,
                  activation: str = "none") -> torch.Tensor | None:
    """``activation(x @ weight.T + bias)`` through oneDNN, or None where the path does not apply.

    Args:
        x: [..., C_in]; weight: [C_out, C_in]; bias: [C_out] or None. CPU tensors.
        activation: "none" or "gelu" (exact, erf form).

    Returns:
        [..., C_out] in the compute dtype (see ``_compute_dtype``; under bf16 autocast the
        operands are cast to bf16, as autocast's own linear does), or None: the caller runs
        the ATen path.
    """
    dt = _compute_dtype(x, weight, bias)
    if dt is None:
        return None
    x, weight = x.to(dt), weight.to(dt)
    bias = None if bias is None else bias.to(dt)
    try:
        if activation == "gelu":
            return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "gelu", [], "none")
        return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")
    except (RuntimeError, AttributeError, NotImplementedError) as exc:  # a build without oneDNN
        _disable("linear", exc)
        return None


@contextlib.contextmanager
def memory_probe():
    """Inside: :func:`attention` returns MEANINGLESS values (for memory searches only).

    The output has the real one's shape, dtype and allocation (and SDPA's autocast casts of
    q, k, v are made as the real call makes them), filled from V's first rows instead of
    computed. The fused SDPA backends' own workspace (a float32 [B, nh, N] log-sum-exp) is not
    allocated; a math-backend fallback's O(N^2) scores would not be either.
    """
    previous = _STATE["probe"]
    _STATE["probe"] = True
    try:
        yield
    finally:
        _STATE["probe"] = previous


def probing() -> bool:
    """True inside :func:`memory_probe`."""
    return _STATE["probe"]


def _sdpa_dtype(q: torch.Tensor) -> torch.dtype:
    """The dtype SDPA computes and returns: the autocast dtype under autocast (not float64)."""
    dev = q.device.type
    if torch.is_autocast_enabled(dev) and q.dtype != torch.float64:
        return torch.get_autocast_dtype(dev)
    return q.dtype


def _sdpa(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``F.scaled_dot_product_attention(q, k, v)`` -> [B, nh, Nq, D]; the stand-in when probing."""
    if not _STATE["probe"]:
        return F.scaled_dot_product_attention(q, k, v)
    dt = _sdpa_dtype(q)
    q, k, v = q.to(dt), k.to(dt), v.to(dt)  # the copies autocast would make (none when already dt)
    out = torch.empty(*q.shape[:-1], v.shape[-1], dtype=dt, device=q.device)
    out.copy_(v[..., :q.shape[-2], :])
    return out


def attention_query_chunked(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, rows: int) -> torch.Tensor:
    """SDPA of ``rows`` query rows at a time against the full K and V.

    Args:
        q: [B, nh, N, D]; k, v: [B, nh, M, D] (any strides, any device).
        rows: query rows per chunk (>= 1).

    Returns:
        [B, N, nh, D] token-major, equal to ``F.scaled_dot_product_attention(q, k, v)
        .transpose(1, 2)`` within the backend's rounding; the extra memory is one chunk's
        [B, nh, rows, D] output (and, where the backend materialises scores, B x nh x rows x M).
    """
    if rows < 1:
        raise ValueError(f"query chunk must be >= 1 row, got {rows}")
    B, H, N, _ = q.shape
    out = None
    for i in range(0, N, rows):
        part = _sdpa(q[:, :, i:i + rows], k, v).transpose(1, 2)
        if out is None:
            out = torch.empty(B, N, H, v.shape[-1], dtype=part.dtype, device=part.device)
        out[:, i:i + rows] = part
        del part
    if out is None:  # N == 0
        out = torch.empty(B, 0, H, v.shape[-1], dtype=_sdpa_dtype(q), device=q.device)
    return out


def _probe_cpu(q: torch.Tensor, v: torch.Tensor, dt: torch.dtype) -> torch.Tensor:
    """Probe stand-in for the CPU fast paths: [B, N, nh, D] in their output dtype ``dt``."""
    B, H, N, D = q.shape
    out = torch.empty(B, N, H, D, dtype=dt, device=q.device)
    out.copy_(v.transpose(1, 2))
    return out


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Softmax attention without mask, scale 1/sqrt(D).

    Args:
        q, k, v: [B, nh, N, D] (any strides).

    Returns:
        [B, N, nh, D] (token-major, ready for the output projection). In bf16 the fused
        C++ kernel (``_attention_kernel``) where it is available for this D, else the oneDNN
        path where ``_compute_dtype`` allows it, else ``F.scaled_dot_product_attention``
        (off the CPU in query chunks beyond ``QUERY_CHUNK_MIN_ROWS``; see the module docstring).
    """
    dt = _compute_dtype(q, k, v)
    if dt is not None and _STATE["probe"]:
        return _probe_cpu(q, v, dt)
    if dt == torch.bfloat16 and _attention_kernel.supports(q.shape[-1]):
        return _attention_kernel.attention_bf16(q, k, v)
    if dt is not None:
        try:
            return _attention_onednn(q, k, v, dt)
        except (RuntimeError, AttributeError, NotImplementedError) as exc:
            _disable("attention", exc)
    B, H, N, _ = q.shape
    if q.device.type != "cpu" and B * H * N > QUERY_CHUNK_MIN_ROWS:
        return attention_query_chunked(q, k, v, QUERY_CHUNK_ROWS)
    return _sdpa(q, k, v).transpose(1, 2)


def _attention_onednn(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, dt: torch.dtype) -> torch.Tensor:
    """Row-chunked attention: per (batch, head), ATTENTION_CHUNK query rows at a time.

    Scores [chunk, N] in float32 (oneDNN), softmax in float32, then P [chunk, N] @ V [N, D]
    in ``dt`` (float32 accumulation inside oneDNN). Returns [B, N, nh, D] in ``dt``.
    """
    linear = torch.ops.mkldnn._linear_pointwise
    B, H, N, D = q.shape
    out = torch.empty(B, N, H, D, dtype=dt, device=q.device)
    qs = q.float() * (D ** -0.5)
    kf = k.float()
    for b in range(B):
        for h in range(H):
            k_bh = kf[b, h].contiguous()  # [N, D]: the "weight" of scores = q k^T
            v_t = v[b, h].to(dt).t().contiguous()  # [D, N]: the "weight" of P V
            for i in range(0, N, ATTENTION_CHUNK):
                scores = linear(qs[b, h, i:i + ATTENTION_CHUNK], k_bh, None, "none", [], "")
                probs = torch.softmax(scores, dim=-1).to(dt)
                out[b, i:i + ATTENTION_CHUNK, h] = linear(probs, v_t, None, "none", [], "")
    return out
