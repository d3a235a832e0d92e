"""Generated episodes rolled out in B slots that never wait for each other (the fast expansion path's device side).

Each slot holds one planned episode: its state, its own frame counter, its prescribed body poses (B, T, P, 7) and its
trajectory so far, all resident on the device. One `advance` moves every slot one frame: WorldContact's step on the
static-shape path (fixed-K neighbours, bf16 on CUDA), the fixed projection (wc.expand.fixed_projection) and the
one-frame checks (wc.expand.frame_checks), whose first failing frames stay on the device. On CUDA the four parts are
captured as CUDA graphs, replayed every frame; CUDA events between them time each part. The host reads the slots'
first failures every few frames (`read_failures`, one sync); a slot whose episode ended or failed gives its
trajectory back (`take`) and takes the next plan (`load`), so no batch runs half empty. A slot never carries a
non-finite state: a diverged prediction is recorded in its trajectory (and fails `non_finite`) while the state stays.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import torch

from wc.expand.fixed_projection import FixedStepProjection
from wc.expand.frame_checks import FRAME_CHECKS, NEVER, FirstFailures, FrameChecks
from wc.model.layout import SceneLayout
from wc.model.padded_neighbors import NeighborCapacity
from wc.model.rollout import Step, compiled, frame_step
from wc.model.worldcontact import WorldContact

PARTS = ("network", "projection", "untangle", "checks")  # the timed parts of a frame, in order


@dataclass(frozen=True)
class SlotPlan:
    """What a slot rolls out: frame-0 state x0 (N, 3) [m] (v0 = 0) and body poses (T, P, 7) of frames 0..T-1."""

    x0: np.ndarray
    poses: np.ndarray


class SlotRollout:
    """B slots of one scene layout (module docstring). projection: the layout's topology projection P (None: off);
    capacities: the static neighbour capacities; link_columns: the pose columns of scene.link_names; every: the
    self-intersection check's frame stride; frames: the longest episode a slot holds."""

    def __init__(self, model: WorldContact, layout: SceneLayout, projection: torch.nn.Module | None,
                 capacities: dict[str, NeighborCapacity], fixed: FixedStepProjection, checks: FrameChecks,
                 link_columns: list[int], dt: float, batch: int, frames: int, every: int, *, bf16: bool,
                 cuda_graph: bool, compile_network: bool = False, steps: dict[tuple[int, str], Step] | None = None
                 ) -> None:
        self.model, self.layout, self.topology, self.capacities = model, layout, projection, dict(capacities)
        self.fixed, self.checks, self.dt, self.batch, self.frames, self.every = fixed, checks, dt, batch, frames, every
        self.device = layout.attributes.device
        self.bf16 = bf16 and self.device.type == "cuda"
        self.use_graphs = cuda_graph and self.device.type == "cuda"
        self.compile_network = compile_network and self.device.type == "cuda"
        self.steps = {} if steps is None else steps  # network steps by (slot count, capacities), shared by rollouts
        self.link_columns = torch.as_tensor(link_columns, device=self.device)
        n, p = layout.num_vertices, len(layout.bodies)
        z = dict(device=self.device)
        self.x = torch.zeros(batch, n, 3, **z)
        self.v = torch.zeros(batch, n, 3, **z)
        self.poses = torch.zeros(batch, frames, p, 7, **z)
        self.poses[..., 6] = 1.0
        self.traj_x = torch.full((batch, frames, n, 3), float("nan"), **z)
        self.traj_v = torch.full((batch, frames, n, 3), float("nan"), **z)
        self.t = torch.zeros(batch, dtype=torch.long, **z)
        self.length = torch.ones(batch, dtype=torch.long, **z)
        self.failures = FirstFailures(batch, self.device)
        stride = torch.ones(len(FRAME_CHECKS), dtype=torch.long, **z)
        stride[FRAME_CHECKS.index("self_intersection")] = every
        self.stride = stride
        self._build_network()
        self._graphs: list[torch.cuda.CUDAGraph] | None = None
        self._events: list[torch.cuda.Event] = []
        self._pending: list[list[torch.cuda.Event]] = []
        self.part_s = dict.fromkeys(PARTS, 0.0)  # device time per part (CUDA: read at `read_failures`)
        self.advanced = 0  # frames advanced

    @property
    def compiled(self) -> bool:
        """Whether a frame runs code compiled for this slot count (the network's step or the projection's passes)."""
        return self.compile_network or self.fixed.compiled

    def _build_network(self) -> None:
        """CUDA: the static-shape step (fixed-K neighbours, capturable); the CPU: the Verlet-skin neighbour cache
        (the same pairs, searched as needed: cheaper there, and nothing is captured)."""
        static = self.device.type == "cuda"
        self.neighbors = self.model.fixed_neighbors(self.layout, self.capacities) if static else None
        key = (self.batch, repr(sorted(self.capacities.items())))
        if key not in self.steps:  # a rollout of the same slots and capacities (a longer plan's) reuses the step
            cache = None if static else self.model.neighbor_cache(self.layout)
            step = frame_step(self.model, self.layout, self.dt, self.topology, self.neighbors or cache)
            # Inductor fuses the step's small kernels; compiled once per slot count
            self.steps[key] = compiled(step, dynamic=False) if self.compile_network else step
        self.net = self.steps[key]

    # -- the four parts of a frame, each on persistent buffers (capturable) --
    def _network(self) -> None:
        rows = torch.arange(self.batch, device=self.device)
        now = self.poses[rows, self.t]
        self._next = self.poses[rows, (self.t + 1).clamp_max(self.frames - 1)]
        autocast = torch.autocast("cuda", dtype=torch.bfloat16) if self.bf16 else nullcontext()
        with autocast:
            x, v = self.net(self.x, self.v, now, self._next)
        self._x, self._v = x.float(), v.float()

    def _projection(self) -> None:
        self._link = self._next[:, self.link_columns]
        self._x, self._v = self.fixed.joint(self.x, self._x, self._v, self._link, self.dt)

    def _untangle(self) -> None:
        self._x, self._v, self._crossing = self.fixed.untangle(self.x, self._x, self._v, self.dt)

    def _checks(self) -> None:
        bad = self.checks(self._x, self._v, self._link, self._crossing, self.fixed.stats)
        active = self.t + 1 < self.length
        frame = self.t + 1
        counted = active[:, None] & (frame[:, None] % self.stride == 0)
        self.failures.record(bad, frame, counted)
        rows = torch.arange(self.batch, device=self.device)
        at = frame.clamp_max(self.frames - 1)
        keep = ~active[:, None, None]
        self.traj_x[rows, at] = torch.where(keep, self.traj_x[rows, at], self._x)
        self.traj_v[rows, at] = torch.where(keep, self.traj_v[rows, at], self._v)
        finite = (torch.isfinite(self._x).all(dim=-1).all(dim=-1) & torch.isfinite(self._v).all(dim=-1).all(dim=-1)
                  & active)[:, None, None]
        self.x.copy_(torch.where(finite, self._x, self.x))
        self.v.copy_(torch.where(finite, self._v, self.v))
        self.t.add_(active.long())

    def _parts(self) -> list[Callable[[], None]]:
        return [torch.no_grad()(part) for part in (self._network, self._projection, self._untangle, self._checks)]

    def capture(self) -> None:
        """Capture the four parts as CUDA graphs (CUDA with cuda_graph only) on the slots' current contents, which
        the warm-up runs change: load every slot afterwards."""
        if not self.use_graphs:
            return
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(2):  # warm-up: allocator, lazy initialisation, warp module loads
                for part in self._parts():
                    part()
        torch.cuda.current_stream(self.device).wait_stream(side)
        stats = {k: v.clone() for k, v in self.fixed.stats.items()}  # the warm-up's frames are not counted
        graphs = []
        pool = None
        for part in self._parts():
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph, pool=pool):
                part()
            pool = graph.pool()
            graphs.append(graph)
        self._graphs = graphs
        for k, v in stats.items():
            self.fixed.stats[k].copy_(v)
        self._events = [torch.cuda.Event(enable_timing=True) for _ in range(len(PARTS) + 1)]

    def advance(self, frames: int) -> None:
        """Every slot `frames` frames on (asynchronous on CUDA)."""
        self.advanced += frames
        for _ in range(frames):
            if self._graphs is None:
                for name, part in zip(PARTS, self._parts()):
                    started = time.perf_counter()
                    part()
                    if self.device.type == "cpu":  # CUDA without graphs: launches are timed, not the device
                        self.part_s[name] += time.perf_counter() - started
                continue
            self._events[0].record()
            for graph, event in zip(self._graphs, self._events[1:]):
                graph.replay()
                event.record()
            self._pending.append(list(self._events))
            self._events = [torch.cuda.Event(enable_timing=True) for _ in range(len(PARTS) + 1)]

    def read_failures(self) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
        """(frame counter (B,), first failing frame of each FRAME_CHECKS predicate (B, 5) with NEVER for none, the
        network's neighbour overflow per set): one host sync; on CUDA the part timings are read too."""
        t, frames = self.t.cpu().numpy(), self.failures.frames.cpu().numpy()
        for events in self._pending:
            for name, a, b in zip(PARTS, events[:-1], events[1:]):
                self.part_s[name] += a.elapsed_time(b) / 1000.0
        self._pending = []
        return t, frames, self.neighbors.overflowed() if self.neighbors is not None else {}

    def load(self, slots: list[int], plans: list[SlotPlan]) -> None:
        """Slots take new episodes: frame 0, the poses padded to `frames` by their last pose, counters reset."""
        for s, plan in zip(slots, plans):
            length = len(plan.poses)
            if length > self.frames:
                raise ValueError(f"a planned episode of {length} frames does not fit the slots' {self.frames}")
            poses = torch.as_tensor(plan.poses, dtype=torch.float32, device=self.device)
            self.poses[s, :length] = poses
            self.poses[s, length:] = poses[-1]
            x0 = torch.as_tensor(plan.x0, dtype=torch.float32, device=self.device)
            self.x[s], self.v[s] = x0, 0.0
            self.traj_x[s].fill_(float("nan"))
            self.traj_v[s].fill_(float("nan"))
            self.traj_x[s, 0], self.traj_v[s, 0] = x0, 0.0
            self.t[s], self.length[s] = 0, length
        mask = torch.zeros(self.batch, dtype=torch.bool, device=self.device)
        mask[slots] = True
        self.failures.reset(mask)
        self.fixed.prepare(self.x)
        self._check_first_frames(mask)

    def adopt(self, other: SlotRollout, slots: list[int]) -> None:
        """Slots 0..k-1 take over the episodes in `other`'s `slots` where they stand (state, frame counter, poses,
        trajectory so far, first failures); slots of this rollout from k on keep what they hold. Its slots may hold
        longer episodes than other's (poses padded by their last one)."""
        if len(slots) > self.batch or other.frames > self.frames:
            raise ValueError(f"{len(slots)} episodes of {other.frames} frames do not fit {self.batch} slots of "
                             f"{self.frames}")
        index = torch.as_tensor(slots, dtype=torch.long, device=self.device)
        k, f = len(slots), other.frames
        for name in ("x", "v", "t", "length"):
            getattr(self, name)[:k] = getattr(other, name)[index]
        for name in ("poses", "traj_x", "traj_v"):
            getattr(self, name)[:k, :f] = getattr(other, name)[index]
        self.poses[:k, f:] = other.poses[index, f - 1:f]
        self.traj_x[:k, f:], self.traj_v[:k, f:] = float("nan"), float("nan")
        self.failures.frames[:k] = other.failures.frames[index]
        self.fixed.prepare(self.x)

    @torch.no_grad()
    def _check_first_frames(self, loaded: torch.Tensor) -> None:
        """The one-frame checks on the loaded slots' frame 0 (a planned state can fail them: a parent that crosses
        itself, a bag outside the workspace), recorded as failures at frame 0."""
        _, crossing = self.fixed.rollback.crossings(self.fixed.bvh, self.x)
        bad = self.checks(self.x, self.v, self.poses[:, 0, self.link_columns], crossing)
        self.failures.record(bad, torch.zeros_like(self.t), loaded[:, None].expand_as(bad))

    def take(self, slots: list[int], frames: list[int]) -> list[tuple[np.ndarray, np.ndarray]]:
        """The trajectories (x, v) (T_s, N, 3) of slots, the first frames[s] + 1 frames of each (one copy)."""
        if not slots:
            return []
        index = torch.as_tensor(slots, device=self.device)
        xs, vs = self.traj_x[index].cpu().numpy(), self.traj_v[index].cpu().numpy()
        return [(xs[k, :f + 1], vs[k, :f + 1]) for k, f in enumerate(frames)]

    def grow_capacities(self, sets: list[str], capacities: dict[str, NeighborCapacity] | None = None) -> None:
        """After a neighbour overflow: capacities of `sets` doubled (or these capacities), the network rebuilt;
        capture again before advancing."""
        if capacities is not None:
            self.capacities = dict(capacities)
        elif self.neighbors is not None:
            self.capacities = self.neighbors.grown(sets).capacities
        self._build_network()
        self._graphs = None
        self._pending = []


def never(frames: np.ndarray) -> np.ndarray:
    """(B,) bool: slots whose episode has not failed a one-frame check."""
    return (frames >= NEVER).all(axis=1)
