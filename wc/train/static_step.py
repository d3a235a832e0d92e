"""The fast training step: one static-shape computation per scene layout, optionally compiled and CUDA-graphed.

A step is two parts with one host read between them:
1. forward + backward: the batch's windows gathered on the device from `LayoutFrames`, the W-step rollout with
   fixed-K neighbours (`FixedNeighbors`), the loss, the gradients, and a (2,) status [loss, neighbour overflow];
2. the update: gradient clipping and AdamW.
The host reads the status (the step's one sync; under DDP summed over the ranks first, so all take the same branch)
before the update, so a non-finite loss or a neighbour overflow on any rank never reaches the weights: an overflow
grows that layout's capacities (a new static shape: recompiled and recaptured) and the batch is run again. With
`compile`, each frame step is `torch.compile`d (Inductor fuses the model's many small operations); with `cuda_graph`
(CUDA only) both parts are captured once per layout and replayed, so a step costs two graph launches; under
DistributedDataParallel its bucketed gradient all-reduce, overlapped with the backward, is captured with it (NCCL
collectives can be; the DDP wrapper is built on a side stream and runs 11 eager steps first, as torch requires). Off
both, the same code runs eagerly: the reference that the tests compare with the original pair-list path.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from wc.model.fixed_neighbors import FixedNeighbors
from wc.model.layout import SceneLayout
from wc.model.rollout import compiled, frame_step
from wc.model.worldcontact import WorldContact
from wc.train import distributed
from wc.train.config import TrainConfig
from wc.train.evaluation import segment_loss
from wc.train.noise import noisy_state
from wc.train.resident import LayoutFrames


WARMUP = 2  # eager steps before a capture (compilation, lazily made state)
WARMUP_DDP = 11  # under DistributedDataParallel: torch's rule for capturing its backward (its buckets settle first)


class NeighborOverflow(RuntimeError):
    """More neighbours within a radius than the static capacity holds (the step did not update the weights)."""


def set_learning_rate(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Set every group's lr: in place when it is a tensor (a captured optimizer reads it from the device)."""
    for group in optimizer.param_groups:
        if isinstance(group["lr"], torch.Tensor):
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr


def make_optimizer(model: nn.Module, cfg: TrainConfig, device: torch.device) -> torch.optim.AdamW:
    """AdamW as the paper's; with CUDA graphs capturable, its lr a device tensor."""
    graphed = cfg.cuda_graph and device.type == "cuda"
    lr: float | torch.Tensor = torch.tensor(cfg.base.start_lr, device=device) if graphed else cfg.base.start_lr
    return torch.optim.AdamW(model.parameters(), lr=lr, betas=cfg.betas, weight_decay=cfg.weight_decay,
                             capturable=graphed, foreach=device.type == "cuda")


def initialise_optimizer_state(optimizer: torch.optim.Optimizer) -> None:
    """Create AdamW's moment buffers without changing anything (a capture must not allocate them): one step with
    zero gradients and lr 0, then the step counters back to 0."""
    if all(len(optimizer.state[p]) for g in optimizer.param_groups for p in g["params"]):
        return
    saved = [(g["lr"].clone() if isinstance(g["lr"], torch.Tensor) else g["lr"]) for g in optimizer.param_groups]
    for g in optimizer.param_groups:
        for p in g["params"]:
            p.grad = torch.zeros_like(p)
    set_learning_rate(optimizer, 0.0)
    optimizer.step()
    for g, lr in zip(optimizer.param_groups, saved):
        if isinstance(lr, torch.Tensor):
            g["lr"].copy_(lr)
        else:
            g["lr"] = lr
        for p in g["params"]:
            optimizer.state[p]["step"].zero_()
            p.grad = None


@dataclass
class StepSettings:
    window: int
    batch_size: int
    dt: float
    lambda_x: float
    lambda_v: float
    grad_clip: float
    autocast_bf16: bool
    compile: bool
    cuda_graph: bool
    compile_dynamic: bool = False
    input_noise_m: float = 0.0

    @classmethod
    def of(cls, cfg: TrainConfig, dt: float) -> StepSettings:
        return cls(cfg.window, cfg.batch_size, dt, cfg.lambda_x, cfg.lambda_v, cfg.grad_clip, cfg.autocast_bf16,
                   cfg.compile, cfg.cuda_graph, cfg.compile_dynamic, cfg.input_noise_m)


class LayoutStep:
    """Forward + backward and the update of one layout's batches, as static shapes (see the module doc)."""

    def __init__(self, model: WorldContact, runner: nn.Module, optimizer: torch.optim.Optimizer, layout: SceneLayout,
                 frames: LayoutFrames, neighbors: FixedNeighbors, projection: nn.Module | None,
                 settings: StepSettings) -> None:
        self.model, self.runner, self.optimizer = model, runner, optimizer
        self.layout, self.frames, self.neighbors, self.projection = layout, frames, neighbors, projection
        self.s = settings
        self.device = frames.x.device
        self.starts = torch.zeros(settings.batch_size, dtype=torch.long, device=self.device)
        self.graphed = settings.cuda_graph and self.device.type == "cuda"
        step = frame_step(model, layout, settings.dt, projection, neighbors)
        self.frame = compiled(step, settings.compile_dynamic) if settings.compile else step
        self._graphs: tuple[torch.cuda.CUDAGraph, torch.cuda.CUDAGraph, torch.Tensor] | None = None

    def _forward_backward(self) -> torch.Tensor:
        """Gradients of the batch at `self.starts` into .grad; returns [loss, overflow] (2,) on the device."""
        self.neighbors.reset()
        x, v, poses = self.frames.gather(self.starts, self.s.window)
        autocast = (torch.autocast("cuda", dtype=torch.bfloat16) if self.s.autocast_bf16 and self.device.type == "cuda"
                    else nullcontext())
        x0, v0 = noisy_state(x[:, 0], v[:, 0], self.s.input_noise_m, self.s.dt)
        with autocast:
            xp, vp = self.runner(self.layout, x0, v0, poses, self.s.dt, self.projection, self.neighbors, self.frame)
        loss = segment_loss(xp.float(), vp.float(), x[:, 1:], v[:, 1:], self.s.lambda_x, self.s.lambda_v)
        loss.backward()
        return torch.stack((loss.detach(), self.neighbors.overflow.sum().to(loss.dtype)))

    def _update(self) -> None:
        if self.s.grad_clip > 0:
            params = [p for g in self.optimizer.param_groups for p in g["params"] if p.grad is not None]
            torch.nn.utils.clip_grad_norm_(params, self.s.grad_clip, foreach=self.device.type == "cuda")
        self.optimizer.step()

    def _capture(self) -> None:
        """Warm up (compilation) on a side stream, then capture both parts; weights, optimizer state and the RNG
        are restored afterwards, so capturing changes nothing."""
        initialise_optimizer_state(self.optimizer)
        params = [p for g in self.optimizer.param_groups for p in g["params"]]
        saved = [p.detach().clone() for p in params]
        saved_state = {p: {k: v.clone() for k, v in self.optimizer.state[p].items()} for p in params}
        rng = torch.cuda.get_rng_state(self.device)
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(WARMUP_DDP if distributed.world_size() > 1 else WARMUP):
                self.optimizer.zero_grad(set_to_none=True)
                self._forward_backward()
                self._update()
        torch.cuda.current_stream(self.device).wait_stream(side)
        self.optimizer.zero_grad(set_to_none=True)
        backward_graph, update_graph = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(backward_graph):
            status = self._forward_backward()
        with torch.cuda.graph(update_graph):
            self._update()
        with torch.no_grad():
            for p, s in zip(params, saved):
                p.copy_(s)
                for k, v in saved_state[p].items():
                    self.optimizer.state[p][k].copy_(v)
        torch.cuda.set_rng_state(rng, self.device)
        self._graphs = (backward_graph, update_graph, status)

    def forward_backward(self, starts: np.ndarray) -> torch.Tensor:
        """Run part 1 on windows starting at frames `starts` (B,); returns the device status [loss, overflow]."""
        if len(starts) != self.s.batch_size:
            raise ValueError(f"batch of {len(starts)} windows, the step was built for {self.s.batch_size}")
        host = torch.as_tensor(np.asarray(starts, dtype=np.int64))
        self.starts.copy_(host.pin_memory() if self.device.type == "cuda" else host, non_blocking=True)
        if not self.graphed:
            self.optimizer.zero_grad(set_to_none=True)
            return self._forward_backward()
        if self._graphs is None:
            self._capture()
        self._graphs[0].replay()
        return self._graphs[2]

    def update(self) -> None:
        """Run part 2 (after `forward_backward`)."""
        if self.graphed:
            self._graphs[1].replay()
        else:
            self._update()


class StaticTrainer:
    """Optimisation steps on resident windows through one `LayoutStep` per (layout, stage), built on first use."""

    def __init__(self, model: WorldContact, runner: nn.Module, optimizer: torch.optim.Optimizer,
                 capacities: dict[str, Any], settings: StepSettings) -> None:
        self.model, self.runner, self.optimizer, self.settings = model, runner, optimizer, settings
        self.capacities = dict(capacities)
        self.steps: dict[tuple[int, bool], LayoutStep] = {}
        self.grown: list[dict[str, Any]] = []

    def step(self, layout_index: int, layout: SceneLayout, frames: LayoutFrames, starts: np.ndarray,
             projection: nn.Module | None, step_number: int) -> float:
        """One AdamW step on the windows at `starts`; returns the loss. Raises FloatingPointError on a non-finite
        loss (before any update)."""
        while True:
            key = (layout_index, projection is not None)
            if key not in self.steps:
                neighbors = self.model.fixed_neighbors(layout, self.capacities)
                self.steps[key] = LayoutStep(self.model, self.runner, self.optimizer, layout, frames, neighbors,
                                             projection, self.settings)
            layout_step = self.steps[key]
            status = distributed.summed(layout_step.forward_backward(starts).clone())  # every rank's [loss, overflow]
            loss, overflow = status.tolist()  # the step's one host sync
            loss /= distributed.world_size()
            if not overflow:
                break
            self._grow(layout_step, step_number)
        if not np.isfinite(loss):
            raise FloatingPointError(f"train: loss became {loss} at step {step_number}")
        layout_step.update()
        return loss

    def release(self) -> None:
        """Drop every layout's step and its CUDA graphs, before the process group ends: a captured NCCL all-reduce
        holds its communicator, whose destruction then never returns (seen on two H200s)."""
        self.steps.clear()
        if torch.cuda.is_available():
            torch.cuda.synchronize()

    def _grow(self, layout_step: LayoutStep, step_number: int) -> None:
        """Double the capacities of the sets that overflowed; every step is rebuilt with them."""
        over = layout_step.neighbors.overflowed()
        bigger = layout_step.neighbors.grown(sorted(over))
        self.grown.append({"step": step_number, "overflow": over,
                           "capacities": {k: [c.max_neighbors, c.cell_capacity] for k, c in bigger.capacities.items()}})
        self.capacities = bigger.capacities
        self.steps.clear()
