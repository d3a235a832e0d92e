"""The PropNet / DPI-Net core shared by the three baselines (Li et al. 2019, as used by RoboCraft,
RoboCook and AdaptiGraph): particle and relation encoders, multi-step propagation, a predictor.

Relations are (receiver, sender) index pairs into one flat node list (the originals multiply by
one-hot matrices Rr, Rs; a gather and a scatter-add compute the same sums). A batch of scenes is
one graph with disjoint node ranges.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
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
    """Node effects after `pstep` propagation steps, and the per-node output of the predictor."""

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
                senders: torch.Tensor, outputs: torch.Tensor) -> torch.Tensor:
        """Effects (len(outputs), width) of the nodes `outputs`, from node inputs (n, node_dim), relation inputs
        (E, relation_dim) and (E,) indices.

        Only the outputs and the ends of relations are propagated: a node that sends no relation cannot
        influence another. The relation propagator's linear map on [relation, effect[r], effect[s]] is split
        into its relation part (computed once) and per-node receiver and sender terms gathered onto edges.
        """
        if relations.shape[0] != receivers.shape[0] or receivers.shape != senders.shape:
            raise ValueError(f"relations {tuple(relations.shape)}, receivers {tuple(receivers.shape)} and senders "
                             f"{tuple(senders.shape)} disagree")
        keep = torch.zeros(nodes.shape[0], dtype=torch.bool, device=nodes.device)
        keep[outputs] = True
        keep[receivers] = True
        keep[senders] = True
        keep = torch.nonzero(keep).squeeze(1)
        remap = torch.empty(nodes.shape[0], dtype=torch.long, device=nodes.device)
        remap[keep] = torch.arange(keep.numel(), device=nodes.device)
        rr, ss = remap[receivers], remap[senders]
        particle_enc = self.particle_encoder(nodes[keep])
        w = self.width
        weight = self.relation_propagator.weight
        to_receiver, to_sender = weight[:, w:2 * w], weight[:, 2 * w:]
        rel_term = F.linear(self.relation_encoder(relations), weight[:, :w], self.relation_propagator.bias)
        effect = torch.zeros_like(particle_enc)
        for i in range(self.pstep):
            if i == 0:  # every effect is still zero
                rel = torch.relu(rel_term)
            else:
                rel = torch.relu(rel_term + F.linear(effect, to_receiver)[rr] + F.linear(effect, to_sender)[ss])
            agg = torch.zeros_like(effect).index_add_(0, rr, rel)
            effect = torch.relu(self.particle_propagator(torch.cat([particle_enc, agg], -1)) + effect)
        return effect[remap[outputs]]

    def forward(self, nodes: torch.Tensor, relations: torch.Tensor, receivers: torch.Tensor,
                senders: torch.Tensor, outputs: torch.Tensor) -> torch.Tensor:
        """Predictor output (len(outputs), out_dim) of the nodes `outputs`."""
        return self.predictor(self.effects(nodes, relations, receivers, senders, outputs))
