"""The PropNet / DPI-Net core shared by the three baselines (Li et al. 2019, as used by RoboCraft,
RoboCook and AdaptiGraph): particle and relation encoders, multi-step propagation, a predictor.

Relations are (receiver, sender) index pairs into one flat node list (the originals multiply by
one-hot matrices Rr, Rs; a gather and a scatter-add compute the same sums). A batch of scenes is
one graph with disjoint node ranges.
"""

from __future__ import annotations

import torch
from torch import nn

WIDTH = 150  # nf in all three originals


def mlp(sizes: list[int], relu_out: bool) -> nn.Sequential:
    """Linear layers of `sizes` with ReLU between them (and after the last if `relu_out`)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if relu_out or i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PropNet(nn.Module):
    """Particle effects after `pstep` propagation steps, and the per-particle output of the predictor."""

    def __init__(self, node_dim: int, relation_dim: int, pstep: int, out_dim: int = 3, width: int = WIDTH) -> None:
        super().__init__()
        self.pstep = pstep
        self.width = width
        self.particle_encoder = mlp([node_dim, width, width, width], relu_out=True)
        self.relation_encoder = mlp([relation_dim, width, width, width], relu_out=True)
        self.relation_propagator = nn.Linear(3 * width, width)
        self.particle_propagator = nn.Linear(2 * width, width)
        self.predictor = mlp([width, width, width, out_dim], relu_out=False)

    def effects(self, nodes: torch.Tensor, relations: torch.Tensor, receivers: torch.Tensor,
                senders: torch.Tensor) -> torch.Tensor:
        """Particle effects (n, width) from node inputs (n, node_dim), relation inputs (E, relation_dim), (E,) indices."""
        if relations.shape[0] != receivers.shape[0] or receivers.shape != senders.shape:
            raise ValueError(f"relations {tuple(relations.shape)}, receivers {tuple(receivers.shape)} and senders "
                             f"{tuple(senders.shape)} disagree")
        particle_enc = self.particle_encoder(nodes)
        relation_enc = self.relation_encoder(relations)
        effect = torch.zeros_like(particle_enc)
        for _ in range(self.pstep):
            rel = torch.relu(self.relation_propagator(torch.cat([relation_enc, effect[receivers], effect[senders]], -1)))
            agg = torch.zeros_like(effect).index_add_(0, receivers, rel)
            effect = torch.relu(self.particle_propagator(torch.cat([particle_enc, agg], -1)) + effect)
        return effect

    def forward(self, nodes: torch.Tensor, relations: torch.Tensor, receivers: torch.Tensor,
                senders: torch.Tensor) -> torch.Tensor:
        """Predictor output (n, out_dim) for every node."""
        return self.predictor(self.effects(nodes, relations, receivers, senders))
