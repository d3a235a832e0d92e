"""What the three particle baselines share: the particle scene of a layout, prescribed-point histories,
edge helpers, the autoregressive particle unroll, the training-window loss and the vertex rollout.

Frames and history: a baseline predicts frame t+1 from the object particles at frames t-H+1..t
(H = `history`) and the prescribed (tool, table) points at frames t-H+1..t+1; the last tool step
t -> t+1 is the action. Before the first frame of a rollout the history is the recorded frames before it where
the rollout is given them (`PastFrames`, as training windows have them); further back, the earliest known frame
moved back at its velocity, x_{-k} = x_e - k v_e dt (so a rollout from an episode's frame 0 starts at v0, not at
rest), with the bodies held at their earliest known pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from wc.baselines.config import BaselineParams
from wc.baselines.sampling import ParticleMap, farthest_points, particle_map
from wc.model.layout import SceneLayout
from wc.model.past_frames import PastFrames
from wc.model.neighbors import radius_pairs
from wc.rotations import quat_rotate_torch


@dataclass
class ParticleScene:
    """The nodes of one layout: object particles, subsampled controllable (tool) points, environment points."""

    particles: ParticleMap
    tool_samples: torch.Tensor  # (Mt,) long: rows of the layout's samples [0, num_controllable)
    tool_body: torch.Tensor  # (Mt,) long: body column of each tool point
    tool_eef: torch.Tensor  # (Mt,) bool: on a finger or a held object (the end effector)
    env_samples: torch.Tensor  # (Me,) long: rows of the layout's samples [num_controllable, M)

    @property
    def num_particles(self) -> int:
        return int(self.particles.vertices.shape[0])


@dataclass
class StepInput:
    """Inputs of one prediction t -> t+1 (B scenes of one layout)."""

    objects: torch.Tensor  # (B, H, K, 3) particle positions at t-H+1..t, m
    tools: torch.Tensor  # (B, H+1, Mt, 3) tool points at t-H+1..t+1, m
    tool_normals: torch.Tensor  # (B, Mt, 3) at t+1
    env: torch.Tensor  # (B, Me, 3) environment points at t+1, m
    env_normals: torch.Tensor  # (B, Me, 3)
    scene: ParticleScene


@dataclass
class Graph:
    """Relations as flat (receiver, sender) node indices; tool relations also by scene and tool body."""

    receivers: torch.Tensor  # (E,) long
    senders: torch.Tensor  # (E,) long
    tool_batch: torch.Tensor  # (Et,) long: scene of each tool -> particle relation
    tool_body: torch.Tensor  # (Et,) long: body column of its tool point


def particle_scene(layout: SceneLayout, particles: int, tool_points_per_body: int) -> ParticleScene:
    """Particles by geodesic FPS, up to `tool_points_per_body` FPS points on each controllable body (cached)."""
    key = f"baselines/scene/{particles}/{tool_points_per_body}"
    if key in layout.cache:
        return layout.cache[key]
    c = layout.num_controllable
    body = layout.sample_body[:c]
    rows = []
    for b in torch.unique(body).tolist():
        idx = torch.nonzero(body == b).squeeze(1)
        rows.append(idx[farthest_points(layout.sample_points[idx], tool_points_per_body)].sort().values)
    tools = torch.cat(rows) if rows else torch.empty(0, dtype=torch.long, device=body.device)
    names = [layout.bodies[int(b)] for b in layout.sample_body[tools].tolist()]
    eef = torch.tensor([("finger" in n) or n.startswith("held_") for n in names], dtype=torch.bool,
                       device=body.device)
    scene = ParticleScene(particle_map(layout, particles), tools, layout.sample_body[tools], eef,
                          torch.arange(c, layout.sample_points.shape[0], device=body.device))
    layout.cache[key] = scene
    return scene


def sample_frames(layout: SceneLayout, poses: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions and normals (B, T, R, 3) of the prescribed samples `rows` (R,) at every frame of poses (B, T, P, 7)."""
    at = poses[:, :, layout.sample_body[rows]]  # (B, T, R, 7)
    local = layout.sample_points[rows].expand_as(at[..., :3])
    x = at[..., :3] + quat_rotate_torch(at[..., 3:], local)
    return x, quat_rotate_torch(at[..., 3:], layout.sample_normals[rows].expand_as(local))


def particle_rows(bsz: int, n: int, k: int, device: torch.device) -> torch.Tensor:
    """Flat node indices (B k,) of the particles: the first k of each scene's n nodes."""
    return (torch.arange(bsz, device=device)[:, None] * n + torch.arange(k, device=device)).flatten()


def radius_edges(receivers: torch.Tensor, senders: torch.Tensor, radius: float,
                 exclude_self: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(scene, receiver, sender, distance) of all pairs closer than `radius` within each scene.

    receivers (B, R, 3), senders (B, S, 3) in m; indices are per-scene; exclude_self drops r == s.
    """
    bsz, r, s = receivers.shape[0], receivers.shape[1], senders.shape[1]
    dev = receivers.device
    q, p = receivers.reshape(-1, 3), senders.reshape(-1, 3)
    qi, pj = radius_pairs(q, p, radius, query_batch=torch.arange(bsz, device=dev).repeat_interleave(r),
                          point_batch=torch.arange(bsz, device=dev).repeat_interleave(s), exclude_self=exclude_self)
    return qi // max(r, 1), qi % max(r, 1), pj % max(s, 1), (p[pj] - q[qi]).detach().norm(dim=-1)


def nearest_per_group(group: torch.Tensor, dist: torch.Tensor, k: int) -> torch.Tensor:
    """Mask (E,) keeping, in each group, the k pairs of smallest `dist` (ties: lower index)."""
    if group.numel() == 0:
        return torch.zeros(0, dtype=torch.bool, device=group.device)
    order = torch.argsort(dist, stable=True)
    order = order[torch.argsort(group[order], stable=True)]
    _, counts = torch.unique_consecutive(group[order], return_counts=True)
    starts = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    keep = torch.zeros_like(group, dtype=torch.bool)
    keep[order[torch.arange(order.numel(), device=group.device) - starts < k]] = True
    return keep


def node_types(k: int, mt: int, me: int, device: torch.device) -> torch.Tensor:
    """One-hot (K + Mt + Me, 3) node types: object particle, tool point, floor point."""
    kind = torch.cat([torch.zeros(k), torch.ones(mt), torch.full((me,), 2.0)]).long().to(device)
    return F.one_hot(kind, 3).float()


def radius_graph(step: StepInput, radius_obj: float, radius_tool: float, radius_floor: float,
                     max_per_tool: int | None = None) -> Graph:
    """Particle <-> particle, tool -> particle and floor -> particle relations on flat nodes [K, Mt, Me] per scene."""
    p = step.objects[:, -1]
    bsz, k = p.shape[:2]
    mt, me = step.tools.shape[2], step.env.shape[1]
    n = k + mt + me
    b, r, s, _ = radius_edges(p, p, radius_obj, exclude_self=True)
    recv, send = [b * n + r], [b * n + s]
    tb, tr, ts, td = radius_edges(p, step.tools[:, -1], radius_tool)
    if max_per_tool is not None:  # RoboCook: each tool point touches at most its nearest few particles
        keep = nearest_per_group(tb * max(mt, 1) + ts, td, max_per_tool)
        tb, tr, ts = tb[keep], tr[keep], ts[keep]
    recv.append(tb * n + tr)
    send.append(tb * n + k + ts)
    fb, fr, fs, fd = radius_edges(p, step.env, radius_floor)
    keep = nearest_per_group(fb * k + fr, fd, 1)  # the floor is a plane: its nearest point says all
    fb, fr, fs = fb[keep], fr[keep], fs[keep]
    recv.append(fb * n + fr)
    send.append(fb * n + k + mt + fs)
    return Graph(torch.cat(recv), torch.cat(send), tb, step.scene.tool_body[ts])


def start_history(x0: torch.Tensor, v0: torch.Tensor, poses0: torch.Tensor, dt: float, count: int,
                  past: PastFrames | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (B, count + 1, N, 3) of frames -count..0 and body poses (B, count, P, 7) of frames -count..-1.

    x0, v0 (B, N, 3) m, m/s and poses0 (B, P, 7) are frame 0. The last frames of `past` are used where it has them;
    before the earliest known frame e, x_{-k} = x_e - k v_e dt (dt in s) and the bodies keep e's pose.
    """
    xs, vs, ps = x0[:, None], v0[:, None], poses0[:, None]
    if past is not None and past.x.shape[1]:
        xs = torch.cat([past.x.to(x0), xs], 1)[:, -(count + 1):]
        vs = torch.cat([past.v.to(v0), vs], 1)[:, -(count + 1):]
        ps = torch.cat([past.poses.to(poses0), ps], 1)[:, -(count + 1):]
    missing = count + 1 - xs.shape[1]
    k = torch.arange(missing, 0, -1, dtype=x0.dtype, device=x0.device)[None, :, None, None]
    xs = torch.cat([xs[:, :1] - k * dt * vs[:, :1], xs], 1)
    ps = torch.cat([ps[:, :1].expand(-1, missing, -1, -1), ps], 1)
    return xs, ps[:, :-1]


class ParticleDynamics(nn.Module):
    """A particle baseline. Subclasses give `predict` (one step) and `particle_loss`, and the class facts."""

    name: ClassVar[str]
    history: ClassVar[int] = 4  # n_his: frames of particle history, the current one included
    sequence: ClassVar[int]  # predicted steps per training window (gradients through all)
    rebuild_in_training: ClassVar[bool] = True  # rebuild the relations at every step of the training unroll
    plateau: ClassVar[bool] = False  # ReduceLROnPlateau on the validation loss

    def __init__(self, params: BaselineParams) -> None:
        super().__init__()
        self.params = params
        # data statistics (set by set_statistics before training; saved with the weights)
        self.register_buffer("position_mean", torch.zeros(3))
        self.register_buffer("position_std", torch.ones(3))
        self.register_buffer("displacement_std", torch.ones(()))

    def set_statistics(self, position_mean: torch.Tensor, position_std: torch.Tensor, displacement_std: float) -> None:
        """Fixed input normalisation: positions per axis (m), per-frame displacements (m)."""
        self.position_mean.copy_(position_mean)
        self.position_std.copy_(position_std)
        self.displacement_std.fill_(displacement_std)

    def predict(self, step: StepInput, graph: Graph | None) -> tuple[torch.Tensor, Graph]:
        """Particle positions (B, K, 3) at t+1 and the relations used (pass them back in to reuse them)."""
        raise NotImplementedError

    def particle_loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Training loss of predicted particles (B, S, K, 3) against the true ones."""
        raise NotImplementedError

    def scene(self, layout: SceneLayout) -> ParticleScene:
        return particle_scene(layout, self.params.particles, self.params.tool_points_per_body)

    def unroll(self, layout: SceneLayout, objects: torch.Tensor, poses: torch.Tensor, rebuild: bool) -> torch.Tensor:
        """Particles (B, S, K, 3) predicted autoregressively from particle history (B, H, K, 3) and body poses
        (B, H + S, P, 7) (frames t-H+1 .. t+S); relations rebuilt every step or kept from the first."""
        h = self.history
        if objects.ndim != 4 or objects.shape[1] != h or poses.ndim != 4 or poses.shape[1] < h + 1:
            raise ValueError(f"{self.name}: need particle history (B, {h}, K, 3) and poses (B, >= {h + 1}, P, 7), "
                             f"got {tuple(objects.shape)} and {tuple(poses.shape)}")
        sc = self.scene(layout)
        mt = sc.tool_samples.shape[0]
        points, normals = sample_frames(layout, poses, torch.cat([sc.tool_samples, sc.env_samples]))
        tools, tool_normals = points[:, :, :mt], normals[:, :, :mt]
        env, env_normals = points[:, :, mt:], normals[:, :, mt:]
        hist, graph, out = objects, None, []
        for s in range(poses.shape[1] - h):
            step = StepInput(hist, tools[:, s:s + h + 1], tool_normals[:, s + h], env[:, s + h], env_normals[:, s + h], sc)
            nxt, graph = self.predict(step, None if rebuild else graph)
            out.append(nxt)
            hist = torch.cat([hist[:, 1:], nxt[:, None]], 1)
        return torch.stack(out, 1)

    def window_loss(self, layout: SceneLayout, x: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
        """Loss on training windows x (B, H + S, N, 3), poses (B, H + S, P, 7): H observed frames, S predicted."""
        if x.shape[1] != self.history + self.sequence or poses.shape[1] != x.shape[1]:
            raise ValueError(f"{self.name}: windows must have {self.history + self.sequence} frames, "
                             f"got x {tuple(x.shape)}, poses {tuple(poses.shape)}")
        idx = self.scene(layout).particles.vertices
        pred = self.unroll(layout, x[:, :self.history, idx], poses, self.rebuild_in_training)
        return self.particle_loss(pred, x[:, self.history:, idx])

    @torch.no_grad()
    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float, past: PastFrames | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Every vertex's (x, v), each (B, T-1, N, 3), for frames 1..T-1 from x0, v0 (B, N, 3), poses (B, T, P, 7).

        The particle history before frame 0 is `start_history`: the recorded frames of `past` (B, K, ...) where
        given, else frame 0 moved back at v0. v is the finite difference of the mapped positions over dt (s).
        """
        if x0.ndim != 3 or x0.shape[1:] != (layout.num_vertices, 3) or v0.shape != x0.shape:
            raise ValueError(f"{self.name}: x0 and v0 must be (B, {layout.num_vertices}, 3), "
                             f"got {tuple(x0.shape)} and {tuple(v0.shape)}")
        if poses.ndim != 4 or poses.shape[0] != x0.shape[0] or poses.shape[1] < 2:
            raise ValueError(f"{self.name}: poses must be (B={x0.shape[0]}, T>=2, P, 7), got {tuple(poses.shape)}")
        if past is not None and (past.x.shape[0] != x0.shape[0] or past.x.shape[2:] != x0.shape[1:]
                                 or past.poses.shape[2:] != poses.shape[2:]):
            raise ValueError(f"{self.name}: past frames x {tuple(past.x.shape)}, poses {tuple(past.poses.shape)} do "
                             f"not match x0 {tuple(x0.shape)} and poses {tuple(poses.shape)}")
        pmap = self.scene(layout).particles
        history, before = start_history(x0, v0, poses[:, 0], dt, self.history - 1, past)
        p0 = x0[:, pmap.vertices]
        particles = self.unroll(layout, history[:, :, pmap.vertices].contiguous(), torch.cat([before, poses], 1),
                                rebuild=True)
        x = pmap.to_vertices(x0, p0, particles)
        v = (x - torch.cat([x0[:, None], x[:, :-1]], 1)) / dt
        return x, v

    def normalised_positions(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.position_mean) / self.position_std
