"""Pointwise output head (paper Eq. state_head): refined vertex token -> (dx, dv)."""

from __future__ import annotations

from torch import Tensor, nn


class StateHead(nn.Module):
    """192 -> 128 -> 128 -> 6 MLP with GELU and a LayerNorm after each hidden layer (42,502 parameters).

    The last layer starts near zero (std 1e-3, zero bias) so an untrained model predicts almost no change.
    """

    def __init__(self, dim: int = 192, hidden: int = 128, out: int = 6) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(dim, hidden), nn.GELU(), nn.LayerNorm(hidden),
            nn.Linear(hidden, hidden), nn.GELU(), nn.LayerNorm(hidden),
            nn.Linear(hidden, out),
        )
        nn.init.normal_(self.mlp[-1].weight, std=1e-3)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, h: Tensor) -> Tensor:
        """Eq. state_head: h (B, N, dim) -> (B, N, 6) = [dx (3), dv (3)] in the caller's normalised units."""
        return self.mlp(h)
