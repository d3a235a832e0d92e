"""Static-shape candidate pairs between a cloth's own mesh elements (vertices, edges, triangles), batched over
episodes: the broad phase of the fixed projection (wc.expand.fixed_projection) and of the crossing test
(wc.expand.crossing_test).

Element centres go on the cell grid of `padded_radius_neighbors` (float32, O(N) per episode, no host sync); the batch
id of an element is (episode, cloth mesh), so elements of different episodes or meshes never pair. Each query gets K
slots; a query whose list lost a candidate (more than K, or a visited cell over capacity) flags its episode in
`dropped`, so that what relies on complete lists (the crossing test) can say so rather than pass silently. The search
radius is the reach asked for plus the elements' bounding radii at `stretch` x their rest size; an episode with an
element stretched beyond that is flagged too (`oversized`). Nothing is bag-specific: every cloth object of a scene.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
import torch
from torch import Tensor

from wc.model.padded_neighbors import NeighborCapacity, capacity_for, neighbor_counts, padded_radius_neighbors
from wc.validate.self_intersection import unique_edges


@dataclass(frozen=True)
class ClothElements:
    """Every cloth mesh of a scene as element tables in the scene's vertex rows."""

    vertices: Tensor  # (V,) rows of the cloth vertices
    vertex_mesh: Tensor  # (V,) cloth mesh index of each
    faces: Tensor  # (F, 3) rows
    face_mesh: Tensor  # (F,)
    edges: Tensor  # (E, 2) rows, each once
    edge_mesh: Tensor  # (E,)
    meshes: int
    face_radius_m: float  # largest rest distance of a triangle corner from its centroid
    edge_half_m: float  # largest rest half-length of an edge
    rows: int  # rows of the scene's state x (every predicted object)

    @classmethod
    def of_scene(cls, scene) -> ClothElements:  # noqa: ANN001 - wc.scene.scene.Scene
        slices = scene.vertex_slices()
        parts = [(slices[n].start, np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64))
                 for n, m in scene.objects.items() if scene.object_kinds[n] == "cloth"]
        rows = sum(len(m.vertices) for m in scene.objects.values())
        vertices, vmesh, faces, fmesh, edges, emesh = [], [], [], [], [], []
        face_radius = edge_half = 0.0
        for k, (start, rest, f) in enumerate(parts):
            e = unique_edges(f).astype(np.int64)
            vertices.append(start + np.arange(len(rest)))
            faces.append(start + f)
            edges.append(start + e)
            vmesh.append(np.full(len(rest), k))
            fmesh.append(np.full(len(f), k))
            emesh.append(np.full(len(e), k))
            corners = rest[f]
            face_radius = max(face_radius, float(np.linalg.norm(corners - corners.mean(1, keepdims=True), axis=-1).max(
                initial=0.0)))
            edge_half = max(edge_half, float(np.linalg.norm(rest[e[:, 1]] - rest[e[:, 0]], axis=-1).max(initial=0.0)) / 2)

        def cat(a: list[np.ndarray], shape: tuple[int, ...]) -> Tensor:
            return torch.as_tensor(np.concatenate(a) if a else np.zeros(shape, np.int64), dtype=torch.long)

        return cls(cat(vertices, (0,)), cat(vmesh, (0,)), cat(faces, (0, 3)), cat(fmesh, (0,)), cat(edges, (0, 2)),
                   cat(emesh, (0,)), len(parts), face_radius, edge_half, rows)

    def to(self, device: torch.device | str) -> ClothElements:
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in fields(self)
                                if isinstance(getattr(self, f.name), Tensor)})

    def face_centres(self, x: Tensor) -> Tensor:
        """(B, F, 3) triangle centroids of states x (B, N, 3)."""
        return x[:, self.faces].mean(dim=2)

    def edge_midpoints(self, x: Tensor) -> Tensor:
        """(B, E, 3)."""
        return x[:, self.edges].mean(dim=2)

    def oversized(self, x: Tensor, stretch: float) -> Tensor:
        """(B,) bool: an episode with a triangle or edge larger than `stretch` x the largest rest one (its pairs
        may lie beyond the search radius)."""
        corners = x[:, self.faces]
        face = (corners - corners.mean(dim=2, keepdim=True)).norm(dim=-1).amax(dim=(1, 2))
        ends = x[:, self.edges]
        edge = (ends[:, :, 1] - ends[:, :, 0]).norm(dim=-1).amax(dim=1) / 2
        return ~((face <= stretch * self.face_radius_m) & (edge <= stretch * self.edge_half_m))


@dataclass
class Candidates:
    """K candidate elements per query element of each episode: other (B, Q, K) local element index (0 in unused
    slots), valid (B, Q, K) bool, dropped (B,) bool (an episode whose lists lost a candidate)."""

    other: Tensor
    valid: Tensor
    dropped: Tensor


def _batch_ids(batch: int, mesh: Tensor, meshes: int) -> Tensor:
    return (torch.arange(batch, device=mesh.device)[:, None] * meshes + mesh[None]).reshape(-1)


def search(query: Tensor, query_mesh: Tensor, points: Tensor, point_mesh: Tensor, meshes: int, radius: float,
           capacity: NeighborCapacity, same_set: bool = False) -> Candidates:
    """Points of the same episode and mesh within `radius` [m] of each query: query (B, Q, 3), points (B, M, 3);
    same_set: query and points are the same elements (an element is not its own candidate)."""
    b, q, m = query.shape[0], query.shape[1], points.shape[1]
    found = padded_radius_neighbors(query.reshape(-1, 3), points.reshape(-1, 3), radius, capacity,
                                    query_batch=_batch_ids(b, query_mesh, meshes),
                                    point_batch=_batch_ids(b, point_mesh, meshes), scenes=max(1, b * meshes),
                                    exclude_self=same_set)
    k = found.index.shape[1]
    first = (torch.arange(b, device=query.device) * m)[:, None, None]
    valid = found.valid.reshape(b, q, k)
    other = torch.where(valid, found.index.reshape(b, q, k) - first, 0)
    return Candidates(other, valid, found.dropped.reshape(b, q).any(dim=1))


def measured_capacity(query: Tensor, query_mesh: Tensor, points: Tensor, point_mesh: Tensor, meshes: int,
                      radius: float, headroom: float, same_set: bool = False) -> NeighborCapacity:
    """Capacities for `search` at this radius: the most candidates and cell points seen in the given states
    (B, Q, 3) / (B, M, 3) x headroom (measured once, host sync)."""
    b = query.shape[0]
    most, cell = neighbor_counts(query.reshape(-1, 3).float(), points.reshape(-1, 3).float(), radius,
                                 query_batch=_batch_ids(b, query_mesh, meshes),
                                 point_batch=_batch_ids(b, point_mesh, meshes), scenes=max(1, b * meshes),
                                 exclude_self=same_set)
    return capacity_for(most, cell, headroom)


def compact(valid: Tensor, capacity: int | None) -> tuple[Tensor, Tensor, Tensor]:
    """The True entries of valid (any shape) as indices (P,) into valid.reshape(-1), their mask (P,) and the count
    that did not fit (()). capacity None: exactly the True entries (reads the count: for the CPU, where nothing is
    captured); else P = capacity slots filled in order by a prefix sum, no host sync (unused slots masked)."""
    flat = valid.reshape(-1)
    if capacity is None:
        idx = flat.nonzero().squeeze(1)
        return idx, torch.ones_like(idx, dtype=torch.bool), flat.new_zeros((), dtype=torch.long)
    pos = flat.long().cumsum(0) - 1
    slot = torch.where(flat & (pos < capacity), pos, capacity)  # slot `capacity` collects what does not fit
    idx = torch.zeros(capacity + 1, dtype=torch.long, device=flat.device)
    idx.scatter_(0, slot, torch.arange(flat.numel(), device=flat.device))
    count = flat.sum()
    return idx[:capacity], torch.arange(capacity, device=flat.device) < count, (count - capacity).clamp_min(0)


def host_checks(t: Tensor) -> bool:
    """Whether loops over tensors on t's device may read values back to stop early (the CPU: nothing is captured in a
    graph and a read costs nothing) or must run their fixed passes (CUDA)."""
    return t.device.type == "cpu"


def gather(x: Tensor, index: Tensor) -> Tensor:
    """x (B, N, ...) at index (B, ...) per episode -> (B, ..., ...)."""
    b = torch.arange(x.shape[0], device=x.device).view(-1, *([1] * (index.ndim - 1)))
    return x[b, index]
