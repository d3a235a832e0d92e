"""Attention building blocks shared by the encoder and decoder: 3D RoPE, multi-head attention, SwiGLU.

Tokens are dense (B, N, C) tensors, anchors (B, N, 3) in metres. Attention always goes through
`torch.nn.functional.scaled_dot_product_attention`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class RoPE3D(nn.Module):
    """3D rotary position embedding on token anchors (WorldParticle's 3D RoPE, dim 24).

    head_dim is split into 3 axes (x, y, z) of head_dim/3 channels each; every axis rotates
    head_dim/6 channel pairs by angle 2*pi*p_axis/lambda_k, with wavelengths lambda_k log-spaced in
    [min_wavelength_m, max_wavelength_m]. The frequencies are fixed buffers: the appendix parameter
    counts leave no room for learnable ones. A pure rotation, so q.k after RoPE depends only on
    the anchor difference.
    """

    def __init__(self, head_dim: int = 24, min_wavelength_m: float = 0.02, max_wavelength_m: float = 2.0) -> None:
        super().__init__()
        if head_dim % 6 != 0:
            raise ValueError(f"head_dim must be divisible by 6 (3 axes x pairs), got {head_dim}")
        if not 0.0 < min_wavelength_m <= max_wavelength_m:
            raise ValueError(f"need 0 < min_wavelength_m <= max_wavelength_m, got {min_wavelength_m}, {max_wavelength_m}")
        self.head_dim = head_dim
        pairs = head_dim // 6  # frequency pairs per axis (4 for head_dim 24)
        wavelengths = torch.logspace(math.log10(min_wavelength_m), math.log10(max_wavelength_m), pairs, dtype=torch.float64)
        self.register_buffer("omega", (2.0 * math.pi / wavelengths).float(), persistent=False)  # (pairs,) [rad/m]

    def angles(self, pos: Tensor) -> Tensor:
        """Rotation angles (B, N, head_dim/2) [rad] from positions (B, N, 3) [m], axis-major; at least float32."""
        pos = pos.to(torch.promote_types(pos.dtype, torch.float32))
        return (pos[..., :, None] * self.omega.to(pos.dtype)).flatten(-2)  # (B, N, 3*pairs)

    def forward(self, t: Tensor, pos: Tensor) -> Tensor:
        """Rotate t (B, heads, N, head_dim) by its anchors pos (B, N, 3); returns t's dtype."""
        theta = self.angles(pos)[:, None]  # (B, 1, N, head_dim/2), >= float32 even under autocast
        cos, sin = theta.cos(), theta.sin()
        tf = t.to(torch.promote_types(t.dtype, theta.dtype)).unflatten(-1, (-1, 2))  # consecutive channel pairs
        t0, t1 = tf[..., 0], tf[..., 1]
        out = torch.stack((t0 * cos - t1 * sin, t0 * sin + t1 * cos), dim=-1).flatten(-2)
        return out.to(t.dtype)


class Attention(nn.Module):
    """Multi-head (self- or cross-) attention with 3D RoPE and optional q/k LayerNorm.

    One biased 192->576 qkv projection (for cross-attention q uses its first third on the query
    tokens, k and v the rest on the context tokens, so both kinds have the same 148,224 parameters
    at width 192) and a biased 192->192 output projection.
    """

    def __init__(self, dim: int = 192, heads: int = 8, qk_norm: bool = False, dropout: float = 0.0,
                 rope: RoPE3D | None = None) -> None:
        super().__init__()
        if dim % heads != 0:
            raise ValueError(f"dim {dim} not divisible by heads {heads}")
        self.dim, self.heads, self.head_dim = dim, heads, dim // heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.q_norm = nn.LayerNorm(dim) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(dim) if qk_norm else nn.Identity()
        self.dropout = dropout
        self.rope = rope if rope is not None else RoPE3D(self.head_dim)
        if self.rope.head_dim != self.head_dim:
            raise ValueError(f"RoPE head_dim {self.rope.head_dim} != attention head_dim {self.head_dim}")

    def _heads(self, t: Tensor) -> Tensor:
        return t.unflatten(-1, (self.heads, self.head_dim)).transpose(1, 2)  # (B, heads, N, head_dim)

    def forward(self, h: Tensor, anchors: Tensor, context: Tensor | None = None, context_anchors: Tensor | None = None,
                return_keys: bool = False) -> Tensor | tuple[Tensor, Tensor]:
        """Attend from h (B, N, C) at anchors (B, N, 3) [m] to context (B, M, C) at context_anchors (B, M, 3).

        context=None is self-attention. Returns (B, N, C); with return_keys also the keys averaged over
        heads after RoPE, (B, M, head_dim), the merge similarity of the encoder.
        """
        if context is None:
            q, k, v = self.qkv(h).chunk(3, dim=-1)
            context_anchors = anchors
        else:
            if context_anchors is None:
                raise ValueError("cross-attention needs context_anchors")
            w, b = self.qkv.weight, self.qkv.bias
            q = F.linear(h, w[: self.dim], b[: self.dim])
            k, v = F.linear(context, w[self.dim:], b[self.dim:]).chunk(2, dim=-1)
        q = self.rope(self._heads(self.q_norm(q)), anchors)
        k = self.rope(self._heads(self.k_norm(k)), context_anchors)
        v = self._heads(v)
        # LayerNorm runs in float32 under autocast; SDPA wants one dtype.
        out = F.scaled_dot_product_attention(q.to(v.dtype), k.to(v.dtype), v,
                                             dropout_p=self.dropout if self.training else 0.0)
        out = self.proj(out.transpose(1, 2).flatten(-2))
        if return_keys:
            return out, k.mean(dim=1)
        return out


class SwiGLU(nn.Module):
    """Gated FFN: w2(silu(w1 x) * w3 x), all three linears biased."""

    def __init__(self, dim: int = 192, hidden: int = 192) -> None:
        super().__init__()
        self.w1 = nn.Linear(dim, hidden)
        self.w3 = nn.Linear(dim, hidden)
        self.w2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        """(..., dim) -> (..., dim)."""
        return self.w2(F.silu(self.w1(x)) * self.w3(x))
