"""Rollouts without gradients on the static-shape path: the training step's frame function, replayed per frame.

One `frame_step` per (layout, batch size, projection) with fixed-K neighbours; optionally `torch.compile`d; on
CUDA captured once as a CUDA graph and replayed every frame (a frame then costs one graph launch instead of
thousands of kernel launches). The overflow count is read once per rollout (or with the finiteness flag of each
frame when the caller stops at the first non-finite frame); an overflow grows the capacities that overflowed, and
the rollout runs again from its first frame, so no neighbour is ever dropped.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass

import torch
from torch import nn

from wc.model.fixed_neighbors import FixedNeighbors
from wc.model.layout import SceneLayout
from wc.model.padded_neighbors import NeighborCapacity
from wc.model.rollout import Step, compiled, frame_step
from wc.model.worldcontact import WorldContact


@dataclass
class _Stepper:
    """A frame step of one (layout, batch, projection): its static inputs / outputs and, on CUDA, its graph."""

    layout: SceneLayout  # held, so the id in the cache key stays valid
    projection: nn.Module | None
    neighbors: FixedNeighbors
    step: Step
    inputs: tuple[torch.Tensor, ...] | None = None  # x, v, poses_now, poses_next
    outputs: tuple[torch.Tensor, torch.Tensor] | None = None
    graph: torch.cuda.CUDAGraph | None = None


class StaticRollout:
    """No-gradient rollouts of `model` (eval mode) through fixed-K neighbours; see the module doc.

    capacities: {set: NeighborCapacity} (e.g. the checkpoint's, measured on its training data); cuda_graph applies
    on CUDA only; autocast_bf16 runs the network in bf16 on CUDA (state in fp32).
    """

    def __init__(self, model: WorldContact, capacities: dict[str, NeighborCapacity], dt: float, *,
                 compile: bool = False, cuda_graph: bool = True, autocast_bf16: bool = False) -> None:
        self.model, self.capacities, self.dt = model, dict(capacities), float(dt)
        self.compile, self.cuda_graph, self.autocast_bf16 = compile, cuda_graph, autocast_bf16
        self._steppers: dict[tuple, _Stepper] = {}
        self.growths = 0

    def _autocast(self, device: torch.device):  # noqa: ANN202
        on = self.autocast_bf16 and device.type == "cuda"
        return torch.autocast("cuda", dtype=torch.bfloat16) if on else nullcontext()

    def _stepper(self, layout: SceneLayout, projection: nn.Module | None, x: torch.Tensor,
                 poses: torch.Tensor) -> _Stepper:
        key = (id(layout), id(projection), tuple(x.shape), tuple(poses.shape[2:]), x.dtype, x.device)
        if key not in self._steppers:
            neighbors = self.model.fixed_neighbors(layout, self.capacities)
            step = frame_step(self.model, layout, self.dt, projection, neighbors)
            if self.compile:
                step = compiled(step)
            stepper = _Stepper(layout, projection, neighbors, step)
            if self.cuda_graph and x.is_cuda:
                self._capture(stepper, x, poses)
            self._steppers[key] = stepper
        return self._steppers[key]

    def _capture(self, stepper: _Stepper, x: torch.Tensor, poses: torch.Tensor) -> None:
        inputs = (x.detach().clone(), torch.zeros_like(x), poses[:, 0].detach().clone(), poses[:, 1].detach().clone())
        side = torch.cuda.Stream(x.device)
        side.wait_stream(torch.cuda.current_stream(x.device))
        with torch.cuda.stream(side), self._autocast(x.device):
            for _ in range(2):  # warm-up: compilation, allocator
                stepper.step(*inputs)
        torch.cuda.current_stream(x.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph), self._autocast(x.device):
            outputs = stepper.step(*inputs)
        stepper.inputs, stepper.outputs, stepper.graph = inputs, outputs, graph

    def _frame(self, stepper: _Stepper, x: torch.Tensor, v: torch.Tensor, now: torch.Tensor,
               nxt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if stepper.graph is None:
            with self._autocast(x.device):
                xn, vn = stepper.step(x, v, now, nxt)
            return xn.to(x.dtype), vn.to(v.dtype)
        for buffer, value in zip(stepper.inputs, (x, v, now, nxt)):
            buffer.copy_(value)
        stepper.graph.replay()
        return stepper.outputs[0].to(x.dtype), stepper.outputs[1].to(v.dtype)

    @torch.no_grad()
    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                projection: nn.Module | None = None, stop_non_finite: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicted x, v (B, T-1, N, 3) from x0, v0 (B, N, 3) under poses (B, T, P, 7). With stop_non_finite the
        frames after the first non-finite one are NaN (one host read per frame); otherwise one read per rollout."""
        if poses.ndim != 4 or poses.shape[0] != x0.shape[0] or poses.shape[1] < 2:
            raise ValueError(f"poses must be (B={x0.shape[0]}, T>=2, P, 7), got {tuple(poses.shape)}")
        if x0.ndim != 3 or x0.shape[1] != layout.num_vertices or v0.shape != x0.shape:
            raise ValueError(f"x0 and v0 must be (B, {layout.num_vertices}, 3), got {tuple(x0.shape)}, {tuple(v0.shape)}")
        while True:
            stepper = self._stepper(layout, projection, x0, poses)
            stepper.neighbors.reset()
            steps = poses.shape[1] - 1
            xs = torch.full((x0.shape[0], steps, *x0.shape[1:]), float("nan"), dtype=x0.dtype, device=x0.device)
            vs = xs.clone()
            x, v = x0, v0
            for t in range(steps):
                x, v = self._frame(stepper, x, v, poses[:, t], poses[:, t + 1])
                xs[:, t], vs[:, t] = x, v
                if stop_non_finite:
                    finite = torch.isfinite(x).all() & torch.isfinite(v).all()
                    if not bool(finite) or int(stepper.neighbors.overflow.sum()):
                        break
            over = stepper.neighbors.overflowed()
            if not over:
                return xs, vs
            self.capacities = stepper.neighbors.grown(sorted(over)).capacities
            self._steppers.clear()
            self.growths += 1
