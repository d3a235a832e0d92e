"""Autoregressive rollout of WorldContact over prescribed body poses (training segments, evaluation, expansion)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from wc.model.fixed_neighbors import FixedNeighbors
from wc.model.layout import SceneLayout, boundary_samples
from wc.model.neighbor_cache import NeighborCache
from wc.model.projection import TopologyProjection
from wc.model.worldcontact import WorldContact, advance


Step = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def frame_step(model: WorldContact, layout: SceneLayout, dt: float, projection: TopologyProjection | None = None,
               neighbors: NeighborCache | FixedNeighbors | None = None) -> Step:
    """One predicted frame as a function (x, v, poses_now, poses_next) -> (x, v) of the layout: the unit that
    the static-shape path compiles and captures. poses (B, P, 7) at t and t+Δt."""
    def step(x: torch.Tensor, v: torch.Tensor, poses_now: torch.Tensor,
             poses_next: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        controllable, environment = boundary_samples(layout, poses_now, poses_next, dt)
        return advance(model, x, v, layout, controllable, environment, dt, projection, neighbors)
    return step


def compiled(step: Step, dynamic: bool = True, backend: str = "inductor") -> Step:
    """`torch.compile` of a frame step (fullgraph: any host sync or data-dependent shape is an error). dynamic: sizes
    stay symbolic, so one graph serves every layout, batch size and neighbour capacity (only Python-level
    differences, such as the number of bodies, compile again); False specialises to the first shapes."""
    if dynamic:
        import torch._dynamo.config as dynamo_config  # noqa: PLC0415

        dynamo_config.specialize_float = True  # radii, Δt and config floats are constants, not graph inputs
        dynamo_config.force_nn_module_property_static_shapes = False  # the projection's buffers carry N
        dynamo_config.force_parameter_static_shapes = False
        import torch.fx.experimental._config as fx_config  # noqa: PLC0415

        fx_config.use_duck_shape = False  # a batch of 3 is not the xyz axis of size 3
    return torch.compile(step, fullgraph=True, dynamic=dynamic, backend=backend)


def rollout(model: WorldContact, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
            dt: float, projection: TopologyProjection | None = None, *, neighbor_skin_m: float | None = None,
            neighbors: NeighborCache | FixedNeighbors | None = None,
            step: Step | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted (x, v), each (B, T-1, N, 3), for frames 1..T-1 from x0, v0 (B, N, 3) and poses (B, T, P, 7).

    Each step feeds the previous prediction back in (gradients flow through every step). Without gradients,
    neighbour pairs are reused across steps through `neighbors` or, by default, the layout's Verlet-skin
    cache (skin: neighbor_skin_m, default the model config's; 0 searches every step). The pairs are the
    same either way; with gradients every step searches afresh (the reference training path). `FixedNeighbors`
    (model.fixed_neighbors) gives the static-shape path: the same result within its capacities, no host sync.
    step: `frame_step(model, layout, dt, projection, neighbors)` or a compiled copy of it (then the other
    arguments only shape-check).
    """
    if poses.ndim != 4 or poses.shape[0] != x0.shape[0] or poses.shape[1] < 2:
        raise ValueError(f"poses must be (B={x0.shape[0]}, T>=2, P, 7), got {tuple(poses.shape)}")
    if step is None:
        if neighbors is None and not torch.is_grad_enabled():
            neighbors = model.neighbor_cache(layout, neighbor_skin_m)
        step = frame_step(model, layout, dt, projection, neighbors)
    x, v = x0, v0
    xs, vs = [], []
    for t in range(poses.shape[1] - 1):
        x, v = step(x, v, poses[:, t], poses[:, t + 1])
        xs.append(x)
        vs.append(v)
    return torch.stack(xs, dim=1), torch.stack(vs, dim=1)


def rollout_within_capacity(model: WorldContact, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor,
                            poses: torch.Tensor, dt: float, projection: TopologyProjection | None,
                            neighbors: FixedNeighbors) -> tuple[torch.Tensor, torch.Tensor, FixedNeighbors]:
    """`rollout` on the static-shape path, checked once at the end: if a neighbour set overflowed its capacity,
    the capacities of the sets that did grow and the rollout runs again. Returns x, v and the neighbours used."""
    while True:
        neighbors.reset()
        x, v = rollout(model, layout, x0, v0, poses, dt, projection, neighbors=neighbors)
        over = neighbors.overflowed()  # one host sync per rollout
        if not over:
            return x, v, neighbors
        neighbors = model.fixed_neighbors(layout, neighbors.grown(sorted(over)).capacities)
