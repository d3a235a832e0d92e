"""RoboCraft (Shi et al., RSS 2022): particle dynamics with a contact-mode gated rigid / non-rigid head.

Nodes: object particles, tool points (every controllable body) and floor (table) points, with a
3-d type attribute. Node state = the H-1 residual displacements and the position, normalised by
fixed statistics (tool residuals end at t+1, so their last one is the action). Relations:
particle <-> particle within `neighbor_radius_m`, tool/floor -> particle within
`neighbor_radius_m + tool_radius_m`; relation input = both ends' attributes and the state
difference. Head by contact mode: no tool body in contact -> the particles stay, one body -> a
rigid motion (quaternion + translation per object), two or more -> per-particle displacements;
each step is clamped to +-`max_step_m` per axis. Loss 0.9 EMD + 0.1 Chamfer over 6 steps.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from wc.baselines.base import Graph, ParticleDynamics, StepInput, node_types, particle_rows, radius_graph
from wc.baselines.config import BaselineParams
from wc.baselines.losses import chamfer, emd
from wc.baselines.propnet import WIDTH, PropNet, mlp
from wc.rotations import quat_rotate_torch

PSTEP = 2
EMD_WEIGHT, CHAMFER_WEIGHT = 0.9, 0.1


class RoboCraft(ParticleDynamics):
    name = "robocraft"
    history = 4
    sequence = 6

    def __init__(self, params: BaselineParams) -> None:
        super().__init__(params)
        state = 3 * (self.history - 1) + 3
        self.net = PropNet(3 + state, 3 + 3 + state, PSTEP)
        self.rigid_head = mlp([WIDTH, WIDTH, WIDTH, 7], relu_out=False)  # quaternion (xyzw) + translation

    def predict(self, step: StepInput, graph: Graph | None) -> tuple[torch.Tensor, Graph]:
        p = step.objects[:, -1]
        bsz, k = p.shape[:2]
        mt, me = step.tools.shape[2], step.env.shape[1]
        scale = self.displacement_std
        residual = torch.cat([torch.diff(step.objects, dim=1), torch.diff(step.tools[:, 1:], dim=1),
                              torch.zeros(bsz, self.history - 1, me, 3, device=p.device)], 2) / scale
        position = self.normalised_positions(torch.cat([p, step.tools[:, -1], step.env], 1))
        state = torch.cat([residual.permute(0, 2, 1, 3).flatten(2), position], -1).flatten(0, 1)  # (B n, 3H)
        attr = node_types(k, mt, me, p.device).repeat(bsz, 1)
        if graph is None:
            r = self.params.neighbor_radius_m
            graph = radius_graph(step, r, r + self.params.tool_radius_m, r + self.params.tool_radius_m)
        rr, ss = graph.receivers, graph.senders
        effect = self.net.effects(torch.cat([attr, state], -1), torch.cat([attr[rr], attr[ss], state[rr] - state[ss]], -1),
                                  rr, ss, particle_rows(bsz, k + mt + me, k, p.device)).view(bsz, k, -1)
        nonrigid = self.net.predictor(effect) * scale
        rigid = self._rigid_motion(effect, p, step.scene.particles.object_id) - p
        mode = self._contact_mode(graph, bsz).view(bsz, 1, 1)
        move = torch.where(mode == 0, torch.zeros_like(p), torch.where(mode == 1, rigid, nonrigid))
        if self.params.max_step_m > 0:
            move = move.clamp(-self.params.max_step_m, self.params.max_step_m)
        return p + move, graph

    def _rigid_motion(self, effect: torch.Tensor, p: torch.Tensor, object_id: torch.Tensor) -> torch.Tensor:
        """Particles moved by one rigid motion per object, from the object's mean particle effect."""
        count = torch.bincount(object_id).clamp(min=1).to(p.dtype)[:, None]
        pooled = torch.zeros(p.shape[0], count.shape[0], effect.shape[-1], device=p.device).index_add_(1, object_id, effect)
        centre = torch.zeros(p.shape[0], count.shape[0], 3, device=p.device).index_add_(1, object_id, p) / count
        out = self.rigid_head(pooled / count)
        q = F.normalize(out[..., :4] + torch.tensor([0.0, 0.0, 0.0, 1.0], device=p.device), dim=-1)
        c = centre[:, object_id]
        return c + quat_rotate_torch(q[:, object_id], p - c) + out[..., 4:][:, object_id] * self.displacement_std

    @staticmethod
    def _contact_mode(graph: Graph, bsz: int) -> torch.Tensor:
        """(B,) 0, 1 or 2: how many distinct tool bodies touch the object (capped at 2)."""
        pairs = torch.unique(graph.tool_batch * 1_000_000 + graph.tool_body)
        return torch.bincount(pairs // 1_000_000, minlength=bsz).clamp(max=2)

    def particle_loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return EMD_WEIGHT * emd(pred, target) + CHAMFER_WEIGHT * chamfer(pred, target)
