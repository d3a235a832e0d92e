"""Model inputs from the trajectory store: the static scene layout and the prescribed samples B_{t+Δt}.

A layout fixes which predicted objects are in S_t (rows of x) and which prescribed bodies carry
samples (robot links, fingers, held objects, the table). Scenes of one layout batch together.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import torch

from wc.data.store import TrajectoryStore
from wc.model.projection import edges_from_faces
from wc.rotations import quat_rotate_torch


@dataclass
class SceneLayout:
    """Static per-layout tensors: attributes c_i, rest topology E, and the sample sets of G and the environment.

    N predicted vertices (objects concatenated in `objects` order), M prescribed samples on the
    bodies `bodies` (episode link columns, then environment bodies).
    """

    objects: tuple[str, ...]
    bodies: tuple[str, ...]
    attributes: torch.Tensor  # (N, 3) [tag * tag_scale, rest u, rest v]
    object_index: torch.Tensor  # (N,) long
    rest_uv: torch.Tensor  # (N, 2) m
    vertex_area: torch.Tensor  # (N,) m^2
    edges: torch.Tensor  # (E, 2) long, rest edges of every object
    rest_lengths: torch.Tensor  # (E,) m
    sample_points: torch.Tensor  # (M, 3) body-local m
    sample_normals: torch.Tensor  # (M, 3) body-local unit
    sample_tags: torch.Tensor  # (M,) tag * tag_scale
    sample_body: torch.Tensor  # (M,) long: column of the body in the stacked poses
    num_controllable: int  # samples [0, num_controllable) ride on robot bodies, the rest on the environment
    cache: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)  # e.g. topology pairs

    @property
    def num_vertices(self) -> int:
        return int(self.attributes.shape[0])

    def to(self, device: torch.device | str) -> SceneLayout:
        moved = {f.name: getattr(self, f.name).to(device) for f in fields(self)
                 if isinstance(getattr(self, f.name), torch.Tensor)}
        return replace(self, **moved, cache={})


@dataclass
class Samples:
    """Prescribed samples at t+Δt: positions, velocities and attributes [tag, normal]."""

    x: torch.Tensor  # (B, M, 3) m
    v: torch.Tensor  # (B, M, 3) m/s
    attributes: torch.Tensor  # (B, M, 4)


def scene_layout(store: TrajectoryStore, objects: list[str], links: list[str], tag_scale: float) -> SceneLayout:
    """The layout of episodes that predict `objects` with the prescribed bodies `links` (+ the store's environment)."""
    unknown = [o for o in objects if o not in store.objects]
    if unknown:
        raise ValueError(f"{store.path}: objects {unknown} are not in the store (has {store.object_names})")
    meshes = [store.objects[o] for o in objects]
    sizes = [m.rest_positions.shape[0] for m in meshes]
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    rest = np.concatenate([m.rest_positions for m in meshes])
    uv = np.concatenate([m.rest_uv for m in meshes])
    tags = np.concatenate([np.full(n, m.tag * tag_scale, np.float32) for m, n in zip(meshes, sizes)])
    edges = torch.cat([edges_from_faces(torch.from_numpy(m.faces.astype(np.int64))) + int(off)
                       for m, off in zip(meshes, offsets[:-1])])
    rest_t = torch.from_numpy(rest.astype(np.float32))
    bodies = tuple(links) + tuple(store.env_names)
    column = {b: i for i, b in enumerate(bodies)}
    # controllable sets first, so one slice splits the samples into C and E at every step
    sets = sorted((s for s in store.prescribed.values() if s.link in column), key=lambda s: s.link in store.env_names)
    if not sets:
        raise ValueError(f"{store.path}: no prescribed sample set on any of {bodies}")
    return SceneLayout(
        objects=tuple(objects), bodies=bodies,
        attributes=torch.from_numpy(np.column_stack([tags, uv]).astype(np.float32)),
        object_index=torch.from_numpy(np.repeat(np.arange(len(meshes)), sizes)),
        rest_uv=torch.from_numpy(uv.astype(np.float32)),
        vertex_area=torch.from_numpy(np.concatenate([m.vertex_area for m in meshes]).astype(np.float32)),
        edges=edges, rest_lengths=(rest_t[edges[:, 1]] - rest_t[edges[:, 0]]).norm(dim=-1),
        sample_points=torch.from_numpy(np.concatenate([s.local_points for s in sets]).astype(np.float32)),
        sample_normals=torch.from_numpy(np.concatenate([s.local_normals for s in sets]).astype(np.float32)),
        sample_tags=torch.from_numpy(np.concatenate([np.full(len(s.local_points), s.tag * tag_scale, np.float32)
                                                     for s in sets])),
        sample_body=torch.from_numpy(np.concatenate([np.full(len(s.local_points), column[s.link]) for s in sets])),
        num_controllable=sum(len(s.local_points) for s in sets if s.link not in store.env_names),
    )


def boundary_samples(layout: SceneLayout, poses_now: torch.Tensor, poses_next: torch.Tensor,
                     dt: float) -> tuple[Samples, Samples]:
    """(controllable, environment) samples at t+Δt from body poses (B, P, 7) at t and t+Δt.

    Positions and normals are posed by the t+Δt poses; velocities are the sample displacement over Δt.
    """
    if poses_now.shape != poses_next.shape or poses_now.ndim != 3 or poses_now.shape[1:] != (len(layout.bodies), 7):
        raise ValueError(f"body poses must both be (B, {len(layout.bodies)}, 7) for bodies {layout.bodies}, "
                         f"got {tuple(poses_now.shape)} and {tuple(poses_next.shape)}")
    at_next = poses_next[:, layout.sample_body]  # (B, M, 7)
    at_now = poses_now[:, layout.sample_body]
    local = layout.sample_points.expand_as(at_next[..., :3])
    x_next = at_next[..., :3] + quat_rotate_torch(at_next[..., 3:], local)
    x_now = at_now[..., :3] + quat_rotate_torch(at_now[..., 3:], local)
    normals = quat_rotate_torch(at_next[..., 3:], layout.sample_normals.expand_as(local))
    tags = layout.sample_tags.expand(x_next.shape[0], -1)[..., None]
    attributes = torch.cat([tags, normals], dim=-1)
    v = (x_next - x_now) / dt
    c = layout.num_controllable
    return (Samples(x_next[:, :c], v[:, :c], attributes[:, :c]),
            Samples(x_next[:, c:], v[:, c:], attributes[:, c:]))
