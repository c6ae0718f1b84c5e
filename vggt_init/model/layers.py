"""Transformer building blocks shared by DINO, the aggregator and the camera head.

Parameter names follow the official checkpoint (``norm1``, ``attn.qkv``, ``attn.q_norm``,
``ls1.gamma``, ``mlp.fc1`` ...). Shapes: B batch of sequences, N tokens, C width,
nh heads, D = C / nh head dim.

Memory at many frames: a :class:`Block` whose input holds more than :data:`TOKEN_CHUNK` tokens
(B x N) runs in pieces when autograd is off (inference). Many short sequences (the frame blocks,
DINO: B = frames) go through the block a group of whole sequences at a time; long sequences (the
global blocks, N = frames x tokens per frame) run the token-wise parts (LayerNorms, qkv projection,
q/k norms and RoPE, output projection, MLP) over TOKEN_CHUNK tokens at a time and attention once
over all tokens. Every row is the same arithmetic as in one pass (a matrix product over fewer rows
may sum in another order: float32 differences ~1e-7), and the transients are bounded by the chunk
instead of [B*N, 4C] MLP activations, a [B*N, 3C] qkv and float32 copies of q and k.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vggt_init.model.fastpath import attention, onednn_linear

__all__ = ["LayerScale", "Linear", "Mlp", "RoPE2D", "Attention", "Block", "TOKEN_CHUNK"]

TOKEN_CHUNK = 1 << 15  # tokens per piece when a block's input holds more (~31 frames at 518x392; read at call time)


def _attention_input_dtype(t: torch.Tensor) -> torch.dtype:
    """The dtype ``F.scaled_dot_product_attention`` computes ``t`` in: the autocast dtype under
    autocast on a non-CPU device (autocast casts every floating input but float64), else t's own.
    On the CPU the fast paths of :mod:`vggt_init.model.fastpath` take the tensors as they come."""
    dev = t.device.type
    if dev != "cpu" and torch.is_autocast_enabled(dev) and t.dtype != torch.float64:
        return torch.get_autocast_dtype(dev)
    return t.dtype


class Linear(nn.Linear):
    """nn.Linear (same parameters and names) whose CPU inference uses oneDNN.

    [..., C_in] -> [..., C_out]; see ``vggt_init.model.fastpath`` for when and why.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = onednn_linear(x, self.weight, self.bias)
        return F.linear(x, self.weight, self.bias) if y is None else y


class LayerScale(nn.Module):
    """Per-channel scale ``x * gamma``; gamma [C]."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    """fc1 -> exact GELU -> fc2. [..., C_in] -> [..., C_out]."""

    def __init__(self, dim_in: int, hidden: int, dim_out: int | None = None, bias: bool = True) -> None:
        super().__init__()
        self.fc1 = Linear(dim_in, hidden, bias=bias)
        self.act = nn.GELU()
        self.fc2 = Linear(hidden, dim_out or dim_in, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = onednn_linear(x, self.fc1.weight, self.fc1.bias, activation="gelu")
        return self.fc2(self.act(self.fc1(x)) if h is None else h)


class RoPE2D(nn.Module):
    """2D rotary position embedding (rotate-half form), no parameters.

    The first half of the head dim is rotated by the row coordinate, the second half by
    the column coordinate; inv_freq_j = 1 / base^(2j / (D/2)). Frequencies, positions and
    angles are computed in float32 (as the reference does) and cast to the token dtype
    before cos/sin.
    """

    def __init__(self, base: float = 100.0) -> None:
        super().__init__()
        self.base = float(base)
        self._cache: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def _tables(self, dim: int, length: int, dtype: torch.dtype, device: torch.device):
        key = (dim, length, dtype, device)
        if key not in self._cache:
            exponents = torch.arange(0, dim, 2, device=device).float() / dim
            inv_freq = 1.0 / (self.base ** exponents)
            positions = torch.arange(length, device=device, dtype=torch.float32)
            angles = (positions[:, None] * inv_freq[None, :]).to(dtype)
            angles = torch.cat((angles, angles), dim=-1)
            self._cache[key] = (angles.cos(), angles.sin())
        return self._cache[key]

    @staticmethod
    def _rotate(x: torch.Tensor, pos: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        c = F.embedding(pos, cos)[:, None]
        s = F.embedding(pos, sin)[:, None]
        half = x.shape[-1] // 2
        rot = torch.cat((-x[..., half:], x[..., :half]), dim=-1)
        return x * c + rot * s

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """x [B, nh, N, D], pos [B, N, 2] int64 (row, col) -> [B, nh, N, D]."""
        dim = x.shape[-1] // 2
        cos, sin = self._tables(dim, int(pos.max()) + 1, x.dtype, x.device)
        rows, cols = x.chunk(2, dim=-1)
        return torch.cat((self._rotate(rows, pos[..., 0], cos, sin),
                          self._rotate(cols, pos[..., 1], cos, sin)), dim=-1)


class Attention(nn.Module):
    """Multi-head self-attention with optional qk LayerNorm and 2D RoPE. [B,N,C] -> [B,N,C]."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True, proj_bias: bool = True,
                 qk_norm: bool = False, qk_norm_eps: float = 1e-5, rope: RoPE2D | None = None) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = Linear(dim, 3 * dim, bias=qkv_bias)
        self.q_norm = nn.LayerNorm(self.head_dim, eps=qk_norm_eps) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim, eps=qk_norm_eps) if qk_norm else nn.Identity()
        self.proj = Linear(dim, dim, bias=proj_bias)
        self.rope = rope

    def heads(self, x: torch.Tensor, pos: torch.Tensor | None = None):
        """x [B, N, C], pos [B, N, 2] or None -> q, k, v [B, nh, N, D] (normed, rotated)."""
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)
        q, k = self.q_norm(q), self.k_norm(k)
        if self.rope is not None and pos is not None:
            q, k = self.rope(q, pos), self.rope(k, pos)
        return q, k, v

    def forward(self, x: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        B, N, C = x.shape
        q, k, v = self.heads(x, pos)
        return self.proj(attention(q, k, v).reshape(B, N, C))


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale on both branches. [B,N,C] -> [B,N,C]."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0, qkv_bias: bool = True,
                 proj_bias: bool = True, ffn_bias: bool = True, eps: float = 1e-5,
                 qk_norm: bool = False, qk_norm_eps: float = 1e-5, rope: RoPE2D | None = None) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = Attention(dim, num_heads, qkv_bias, proj_bias, qk_norm, qk_norm_eps, rope)
        self.ls1 = LayerScale(dim)
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), dim, bias=ffn_bias)
        self.ls2 = LayerScale(dim)

    def forward(self, x: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        B, N, _ = x.shape
        rows = TOKEN_CHUNK
        if B * N > rows and not torch.is_grad_enabled():
            if N <= rows:
                return self._forward_sequences(x, pos, max(1, rows // N))
            return self._forward_tokens(x, pos, rows)
        x = x + self.ls1(self.attn(self.norm1(x), pos))
        return x + self.ls2(self.mlp(self.norm2(x)))

    def _forward_sequences(self, x: torch.Tensor, pos: torch.Tensor | None, step: int) -> torch.Tensor:
        """The block on ``step`` whole sequences at a time (attention stays within a sequence)."""
        y = None
        for b0 in range(0, x.shape[0], step):
            xb = x[b0:b0 + step]
            xb = xb + self.ls1(self.attn(self.norm1(xb), None if pos is None else pos[b0:b0 + step]))
            xb = xb + self.ls2(self.mlp(self.norm2(xb)))
            if y is None:
                y = torch.empty(x.shape, dtype=xb.dtype, device=xb.device)
            y[b0:b0 + step] = xb
            del xb
        return y

    def _forward_tokens(self, x: torch.Tensor, pos: torch.Tensor | None, rows: int) -> torch.Tensor:
        """The block with its token-wise parts ``rows`` tokens at a time, attention over all N.

        q, k, v are stored [B, nh, N, D] in the dtype attention computes them in (bf16 under CUDA
        autocast, as autocast would cast them), the attention output [B, N, nh, D] is projected a
        chunk at a time into the new residual, and the MLP branch is added to it in place.
        """
        B, N, C = x.shape
        attn = self.attn
        q = k = v = None
        for i in range(0, N, rows):
            j = min(N, i + rows)
            parts = attn.heads(self.norm1(x[:, i:j]), None if pos is None else pos[:, i:j])
            if q is None:
                q, k, v = (torch.empty(B, attn.num_heads, N, attn.head_dim, dtype=_attention_input_dtype(t),
                                       device=t.device) for t in parts)
            for dst, src in zip((q, k, v), parts):
                dst[:, :, i:j] = src
            del parts, dst, src  # the loop variables would keep v (and a chunk) alive
        o = attention(q, k, v)  # [B, N, nh, D]
        del q, k, v
        y = None
        for i in range(0, N, rows):
            j = min(N, i + rows)
            r = x[:, i:j] + self.ls1(attn.proj(o[:, i:j].reshape(B, j - i, C)))
            if y is None:
                y = torch.empty(x.shape, dtype=r.dtype, device=r.device)
            y[:, i:j] = r
            del r
        del o
        for i in range(0, N, rows):
            j = min(N, i + rows)
            upd = self.ls2(self.mlp(self.norm2(y[:, i:j])))
            if torch.promote_types(y.dtype, upd.dtype) != y.dtype:  # x + upd would promote: do so once
                y = y.to(torch.promote_types(y.dtype, upd.dtype))
            y[:, i:j].add_(upd)  # y's rows are this block's own: x + upd as in one pass
            del upd
        return y
