"""RoboCook (Shi et al., CoRL 2023): particle dynamics driven by tool motion only.

Nodes: object particles, tool points (every controllable body) and floor (table) points with a
3-d type attribute. Node state (dim 6 + 3H) = normalised position, surface normal (zero on object
particles) and the tool's motion history of H displacements ending at t+1 (zero on particles and
floor: only tool points carry history). Relations: particle <-> particle within
`neighbor_radius_m`; tool -> particle within `tool_radius_m`, each tool point to at most its 4
nearest particles; floor -> particle within `neighbor_radius_m`. A scene with no tool relation
is predicted to stay still; each step is bounded by +-`max_step_m` per axis. Loss 0.8 EMD +
0.2 Chamfer over 4 steps; Adam with ReduceLROnPlateau.
"""

from __future__ import annotations

import torch

from wc.baselines.base import Graph, ParticleDynamics, StepInput, node_types, particle_rows, radius_graph
from wc.baselines.config import BaselineParams
from wc.baselines.losses import chamfer, emd
from wc.baselines.propnet import PropNet

PSTEP = 2
MAX_PARTICLES_PER_TOOL_POINT = 4
EMD_WEIGHT, CHAMFER_WEIGHT = 0.8, 0.2


class RoboCook(ParticleDynamics):
    name = "robocook"
    history = 4
    sequence = 4
    plateau = True

    def __init__(self, params: BaselineParams) -> None:
        super().__init__(params)
        state = 6 + 3 * self.history
        self.net = PropNet(3 + state, 3 + 3 + state, PSTEP)

    def predict(self, step: StepInput, graph: Graph | None) -> tuple[torch.Tensor, Graph]:
        p = step.objects[:, -1]
        bsz, k = p.shape[:2]
        mt, me = step.tools.shape[2], step.env.shape[1]
        zeros = torch.zeros_like
        position = self.normalised_positions(torch.cat([p, step.tools[:, -1], step.env], 1))
        normal = torch.cat([zeros(p), step.tool_normals, step.env_normals], 1)
        tool_motion = torch.diff(step.tools, dim=1).permute(0, 2, 1, 3).flatten(2) / self.displacement_std  # (B, Mt, 3H)
        motion = torch.cat([p.new_zeros(bsz, k, tool_motion.shape[-1]), tool_motion,
                            p.new_zeros(bsz, me, tool_motion.shape[-1])], 1)
        state = torch.cat([position, normal, motion], -1).flatten(0, 1)
        attr = node_types(k, mt, me, p.device).repeat(bsz, 1)
        if graph is None:
            graph = radius_graph(step, self.params.neighbor_radius_m, self.params.tool_radius_m,
                                 self.params.neighbor_radius_m, MAX_PARTICLES_PER_TOOL_POINT)
        rr, ss = graph.receivers, graph.senders
        out = self.net(torch.cat([attr, state], -1), torch.cat([attr[rr], attr[ss], state[rr] - state[ss]], -1), rr, ss,
                       particle_rows(bsz, k + mt + me, k, p.device))
        move = out.view(bsz, k, 3) * self.displacement_std
        touched = torch.bincount(graph.tool_batch, minlength=bsz) > 0
        move = torch.where(touched.view(bsz, 1, 1), move, torch.zeros_like(move))
        if self.params.max_step_m > 0:
            move = move.clamp(-self.params.max_step_m, self.params.max_step_m)
        return p + move, graph

    def particle_loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return EMD_WEIGHT * emd(pred, target) + CHAMFER_WEIGHT * chamfer(pred, target)
