"""Static neighbour capacities from the data: the most neighbours (and the densest grid cell) of each searched
set over the stored frames, with headroom. The tokenizer's queries are rebuilt exactly: vertices at t against
vertices at t (spatial) and against the prescribed samples at t + Δt (environment, controllable)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.fixed_neighbors import SEARCHED_SETS
from wc.model.layout import SceneLayout, boundary_samples
from wc.model.padded_neighbors import NeighborCapacity, capacity_for, neighbor_counts
from wc.train.data import LayoutKey, Phase, read_phase_window


def frame_counts(layout: SceneLayout, cfg: ModelConfig, x: torch.Tensor, poses: torch.Tensor,
                 dt: float) -> dict[str, tuple[int, int]]:
    """(most neighbours, densest cell) per searched set over frames 0..F-2 of x (F, N, 3), poses (F, P, 7)."""
    f, n = x.shape[0] - 1, x.shape[1]
    if f < 1:
        return {}
    controllable, environment = boundary_samples(layout, poses[:-1], poses[1:], dt)
    queries = x[:-1].reshape(f * n, 3).float()
    scene_of = {m: torch.arange(f, device=x.device).repeat_interleave(m) for m in
                {n, environment.x.shape[1], controllable.x.shape[1]}}
    radius = {"spatial": cfg.spatial_radius_m, "environment": cfg.environment_radius_m,
              "controllable": cfg.controllable_radius_m}
    points = {"spatial": queries, "environment": environment.x.reshape(-1, 3).float(),
              "controllable": controllable.x.reshape(-1, 3).float()}
    out = {}
    for name in SEARCHED_SETS:
        m = points[name].shape[0] // f
        out[name] = neighbor_counts(queries, points[name], radius[name], query_batch=scene_of[n],
                                    point_batch=scene_of[m], scenes=f, exclude_self=name == "spatial")
    return out


def data_capacities(store: TrajectoryStore, phases: list[Phase], cfg: ModelConfig,
                    layout_for: Callable[[LayoutKey], SceneLayout], headroom: float,
                    device: torch.device) -> tuple[dict[str, NeighborCapacity], dict[str, list[int]]]:
    """Capacities per searched set (max over every frame of `phases`, times headroom) and the measured maxima
    {set: [most neighbours, densest cell]}."""
    if headroom < 1.0:
        raise ValueError(f"neighbour headroom must be >= 1, got {headroom}")
    most = {name: [0, 0] for name in SEARCHED_SETS}
    for p in phases:
        a = read_phase_window(store, p, p.start, p.stop - p.start)
        x = torch.from_numpy(np.ascontiguousarray(a["x"])).to(device)
        poses = torch.from_numpy(np.ascontiguousarray(a["poses"])).to(device)
        for name, (k, c) in frame_counts(layout_for(p.layout), cfg, x, poses, store.dt).items():
            most[name] = [max(most[name][0], k), max(most[name][1], c)]
    return {name: capacity_for(k, c, headroom) for name, (k, c) in most.items()}, most


def initial_capacities(cfg: ModelConfig, layout: SceneLayout, x0: torch.Tensor, poses: torch.Tensor, dt: float,
                       headroom: float = 2.0) -> dict[str, NeighborCapacity]:
    """Capacities from a rollout's first frame (scene 0 of x0 (B, N, 3), poses (B, T, P, 7)), for a model that
    carries none; a rollout grows them where they overflow."""
    counts = frame_counts(layout, cfg, x0[0].detach().expand(2, -1, -1), poses[0, :2], dt)
    return {name: capacity_for(k, c, headroom) for name, (k, c) in counts.items()}
