"""Global-token decoder: global self-attention, then vertex->global cross-attention (paper Sec.
"Global Token Decoder", Eqs. decoder_self and decoder_cross).
"""

from __future__ import annotations

from torch import Tensor, nn

from wc.model.attention import Attention, RoPE3D, SwiGLU


class DecoderLayer(nn.Module):
    """Global self-attention + vertex->global cross-attention + vertex SwiGLU (372,160 parameters at width 192)."""

    def __init__(self, dim: int, heads: int, ffn_hidden: int, dropout: float, rope: RoPE3D) -> None:
        super().__init__()
        self.norm_global = nn.LayerNorm(dim)
        self.self_attn = Attention(dim, heads, qk_norm=False, dropout=dropout, rope=rope)
        self.norm_query = nn.LayerNorm(dim)
        self.norm_context = nn.LayerNorm(dim)
        self.cross_attn = Attention(dim, heads, qk_norm=False, dropout=dropout, rope=rope)
        self.norm_ffn = nn.LayerNorm(dim)
        self.ffn = SwiGLU(dim, ffn_hidden)
        self.ffn_dropout = nn.Dropout(dropout)

    def forward(self, h: Tensor, x: Tensor, g: Tensor, g_anchors: Tensor) -> tuple[Tensor, Tensor]:
        """h (B, N, C) vertex tokens at x (B, N, 3) [m]; g (B, Ng, C) global tokens at g_anchors (B, Ng, 3) [m]."""
        g = g + self.self_attn(self.norm_global(g), g_anchors)  # Eq. decoder_self
        h = h + self.cross_attn(self.norm_query(h), x, self.norm_context(g), g_anchors)  # Eq. decoder_cross
        h = h + self.ffn_dropout(self.ffn(self.norm_ffn(h)))
        return h, g


class GlobalTokenDecoder(nn.Module):
    """L_d decoder layers; queries are the uncompressed vertex tokens H_d^(0) = H_e^(0)."""

    def __init__(self, dim: int = 192, heads: int = 8, layers: int = 3, ffn_hidden: int = 128, dropout: float = 0.1,
                 rope: RoPE3D | None = None) -> None:
        super().__init__()
        rope = rope if rope is not None else RoPE3D(dim // heads)
        self.layers = nn.ModuleList(DecoderLayer(dim, heads, ffn_hidden, dropout, rope) for _ in range(layers))

    def forward(self, vertex_tokens: Tensor, x: Tensor, global_tokens: Tensor, global_anchors: Tensor) -> Tensor:
        """Eqs. decoder_self + decoder_cross per layer.

        vertex_tokens (B, N, C), x = X_t (B, N, 3) [m], global_tokens (B, Ng, C), global_anchors
        (B, Ng, 3) [m] -> refined vertex tokens H_d^(L_d) (B, N, C).
        """
        h, g = vertex_tokens, global_tokens
        for layer in self.layers:
            h, g = layer(h, x, g, global_anchors)
        return h
