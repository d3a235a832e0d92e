"""Hierarchical token encoder: self-attention with 3D RoPE, then bipartite token merging (paper Sec.
"Hierarchical Token Encoder", Eqs. encoder_attention and merge; WorldParticle's super-token scheme).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from wc.model.attention import Attention, RoPE3D, SwiGLU

# Budget of float32 similarity entries per chunk of A rows (64 MiB); a 10k x 10k matrix is 400 MB.
_SIM_CHUNK_ELEMENTS = 1 << 24


@torch.no_grad()
def _most_similar_b(keys_a: Tensor, keys_b: Tensor) -> Tensor:
    """Index (B, Na) long of the B token with the highest key cosine similarity for every A token."""
    a = nn.functional.normalize(keys_a.float(), dim=-1)
    b = nn.functional.normalize(keys_b.float(), dim=-1).transpose(1, 2)  # (B, D, Nb)
    rows = max(1, _SIM_CHUNK_ELEMENTS // max(1, a.shape[0] * b.shape[-1]))
    with torch.autocast(device_type=a.device.type, enabled=False):  # float32 scores for a stable argmax
        if a.shape[1] <= rows:  # one chunk (a bound, not a size: compiled code stays valid for smaller scenes)
            return torch.bmm(a, b).argmax(dim=-1)
        return torch.cat([torch.bmm(a[:, i:i + rows], b).argmax(dim=-1) for i in range(0, a.shape[1], rows)], dim=1)


def bipartite_merge(h: Tensor, anchors: Tensor, multiplicity: Tensor, keys: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Merge tokens pairwise into ceil(N/2) tokens (paper Eq. merge).

    h (B, N, C), anchors (B, N, 3) [m], multiplicity (B, N), keys (B, N, D) the head-averaged RoPE'd
    keys. Partition A = odd positions, B = even positions; each A token joins its most
    cosine-similar B token (argmax, not differentiated); feature and anchor of each output are the
    multiplicity-weighted means over its group, multiplicities add. Output in the order of B.
    """
    h_b, h_a = h[:, 0::2], h[:, 1::2]
    x_b, x_a = anchors[:, 0::2], anchors[:, 1::2]
    m_b, m_a = multiplicity[:, 0::2].float(), multiplicity[:, 1::2].float()
    if h_a.shape[1] == 0:
        return h_b, x_b, m_b
    dst = _most_similar_b(keys[:, 1::2], keys[:, 0::2])  # (B, Na)

    def pooled(values: Tensor, ones: Tensor) -> Tensor:
        return ones.scatter_add(1, dst[..., None].expand(-1, -1, values.shape[-1]), values)

    m = m_b.scatter_add(1, dst, m_a)  # (B, Nb)
    h_sum = pooled(m_a[..., None] * h_a, m_b[..., None] * h_b)
    x_sum = pooled(m_a[..., None] * x_a, m_b[..., None] * x_b)
    return (h_sum / m[..., None]).to(h.dtype), (x_sum / m[..., None]).to(anchors.dtype), m


class EncoderLevel(nn.Module):
    """One level: pre-norm self-attention with q/k LayerNorm, pre-norm SwiGLU (260,928 parameters at width 192)."""

    def __init__(self, dim: int, heads: int, rope: RoPE3D, dropout: float = 0.0) -> None:
        super().__init__()
        self.norm_attn = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads, qk_norm=True, dropout=dropout, rope=rope)
        self.norm_ffn = nn.LayerNorm(dim)
        self.ffn = SwiGLU(dim, dim)

    def forward(self, h: Tensor, anchors: Tensor) -> tuple[Tensor, Tensor]:
        """Eq. encoder_attention (+ FFN): h (B, N, C) at anchors (B, N, 3) -> (h_hat (B, N, C), keys (B, N, head_dim))."""
        a, keys = self.attn(self.norm_attn(h), anchors, return_keys=True)
        h = h + a
        h = h + self.ffn(self.norm_ffn(h))
        return h, keys


class HierarchicalEncoder(nn.Module):
    """L_e levels of attention + bipartite merging; vertex tokens -> ~N/2^L_e global tokens.

    compress=False is the ablation "no hierarchical compression": the same layers, no merging.
    """

    def __init__(self, dim: int = 192, heads: int = 8, levels: int = 3, rope: RoPE3D | None = None,
                 compress: bool = True, dropout: float = 0.0) -> None:
        super().__init__()
        rope = rope if rope is not None else RoPE3D(dim // heads)
        self.compress = compress
        self.levels = nn.ModuleList(EncoderLevel(dim, heads, rope, dropout) for _ in range(levels))

    def forward(self, h: Tensor, anchors: Tensor, multiplicity: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Eqs. encoder_attention + merge per level.

        h (B, N, C) vertex tokens, anchors (B, N, 3) = X_t [m], multiplicity (B, N) or None (ones) ->
        global tokens (B, Ng, C), global anchors (B, Ng, 3) [m], multiplicity (B, Ng);
        Ng = ceil(N / 2^levels) with compression, N without.
        """
        if multiplicity is None:
            multiplicity = torch.ones(h.shape[:2], device=h.device, dtype=torch.float32)
        for level in self.levels:
            h, keys = level(h, anchors)
            if self.compress:
                h, anchors, multiplicity = bipartite_merge(h, anchors, multiplicity, keys)
        return h, anchors, multiplicity
