"""Autoregressive rollout of WorldContact over prescribed body poses (training segments, evaluation, expansion)."""

from __future__ import annotations

import torch

from wc.model.layout import SceneLayout, boundary_samples
from wc.model.neighbor_cache import NeighborCache
from wc.model.projection import TopologyProjection
from wc.model.worldcontact import WorldContact, advance


def rollout(model: WorldContact, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
            dt: float, projection: TopologyProjection | None = None, *, neighbor_skin_m: float | None = None,
            neighbors: NeighborCache | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted (x, v), each (B, T-1, N, 3), for frames 1..T-1 from x0, v0 (B, N, 3) and poses (B, T, P, 7).

    Each step feeds the previous prediction back in (gradients flow through every step). Without gradients,
    neighbour pairs are reused across steps through `neighbors` or, by default, the layout's Verlet-skin
    cache (skin: neighbor_skin_m, default the model config's; 0 searches every step). The pairs are the
    same either way; with gradients every step searches afresh (the training path).
    """
    if poses.ndim != 4 or poses.shape[0] != x0.shape[0] or poses.shape[1] < 2:
        raise ValueError(f"poses must be (B={x0.shape[0]}, T>=2, P, 7), got {tuple(poses.shape)}")
    if neighbors is None and not torch.is_grad_enabled():
        neighbors = model.neighbor_cache(layout, neighbor_skin_m)
    x, v = x0, v0
    xs, vs = [], []
    for t in range(poses.shape[1] - 1):
        controllable, environment = boundary_samples(layout, poses[:, t], poses[:, t + 1], dt)
        x, v = advance(model, x, v, layout, controllable, environment, dt, projection, neighbors)
        xs.append(x)
        vs.append(v)
    return torch.stack(xs, dim=1), torch.stack(vs, dim=1)
