"""AdaptiGraph (Zhang et al., RSS 2024), cloth setting: a translation-invariant particle graph.

Nodes: object particles and end-effector points (fingers and held objects; no floor nodes, as in
the original). Node input (6) = 2-d attribute (object / end effector), the end effector's action
(its displacement t -> t+1, zero on particles) and a physics parameter (this data has one bag
material: constant 0). Absolute position is not an input. Relation input (5 + 3H) = both ends'
attributes, a group difference (1 when the ends belong to different objects, the end effector
counting as its own group) and the position difference at each of the H history frames.
Relations: particle <-> particle within `neighbor_radius_m`, at most the 5 nearest per receiver;
every end-effector point -> every particle. pstep 3; MSE over 3 steps; the relations of a
training window's first step are kept for its unroll and rebuilt every step at rollout.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from wc.baselines.base import Graph, ParticleDynamics, StepInput, nearest_per_group, particle_rows, radius_edges
from wc.baselines.config import BaselineParams
from wc.baselines.propnet import PropNet

PSTEP = 3
TOP_K = 5


class AdaptiGraph(ParticleDynamics):
    name = "adaptigraph"
    history = 4
    sequence = 3
    rebuild_in_training = False

    def __init__(self, params: BaselineParams) -> None:
        super().__init__(params)
        self.net = PropNet(2 + 3 + 1, 2 + 2 + 1 + 3 * self.history, PSTEP)

    def predict(self, step: StepInput, graph: Graph | None) -> tuple[torch.Tensor, Graph]:
        p = step.objects[:, -1]
        bsz, k = p.shape[:2]
        eef_rows = torch.nonzero(step.scene.tool_eef).squeeze(1)
        eef = step.tools[:, :, eef_rows]  # (B, H+1, Me, 3)
        me = eef.shape[2]
        n = k + me
        kind = torch.cat([torch.zeros(k), torch.ones(me)]).long().to(p.device)
        attr = F.one_hot(kind, 2).float().repeat(bsz, 1)
        action = torch.cat([torch.zeros_like(p), eef[:, -1] - eef[:, -2]], 1) / self.displacement_std
        nodes = torch.cat([attr, action.flatten(0, 1), attr.new_zeros(bsz * n, 1)], -1)
        if graph is None:
            graph = self._graph(p, step.scene.tool_body[eef_rows], me)
        rr, ss = graph.receivers, graph.senders
        group = torch.cat([step.scene.particles.object_id, torch.full((me,), -1, device=p.device)]).repeat(bsz)
        hist = torch.cat([step.objects, eef[:, :-1]], 2).permute(0, 2, 1, 3).flatten(0, 1)  # (B n, H, 3)
        offsets = ((hist[rr] - hist[ss]) / self.position_std).flatten(1)
        relations = torch.cat([attr[rr], attr[ss], (group[rr] != group[ss]).float()[:, None], offsets], -1)
        out = self.net(nodes, relations, rr, ss, particle_rows(bsz, n, k, p.device))
        move = out.view(bsz, k, 3) * self.displacement_std
        return p + move, graph

    def _graph(self, p: torch.Tensor, eef_body: torch.Tensor, me: int) -> Graph:
        bsz, k = p.shape[:2]
        n = k + me
        b, r, s, d = radius_edges(p, p, self.params.neighbor_radius_m, exclude_self=True)
        keep = nearest_per_group(b * k + r, d, TOP_K)
        b, r, s = b[keep], r[keep], s[keep]
        eb = torch.arange(bsz, device=p.device).repeat_interleave(me * k)
        er = torch.arange(k, device=p.device).repeat(bsz * me)
        es = torch.arange(me, device=p.device).repeat_interleave(k).repeat(bsz)
        return Graph(torch.cat([b * n + r, eb * n + er]), torch.cat([b * n + s, eb * n + k + es]), eb, eef_body[es])

    def particle_loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return (pred - target).square().mean()
