"""Cloth self-crossings of a batch of states, static-shape and on the device: the rollback guard's test and the
self-intersection check of the fast expansion path (wc.expand.fixed_untangle, wc.expand.frame_checks).

The test is the validate stage's (wc.validate.self_intersection): a cloth mesh self-intersects where one of its edges
crosses a triangle of the same mesh that does not share a vertex with it. Here every edge meets the triangles whose
centroid lies within (edge half-length + triangle radius) of its midpoint, found on a cell grid
(wc.expand.element_pairs), in an exact segment-triangle test (Moeller-Trumbore) in float32, as warp's ray casts are.
An episode whose candidate lists were incomplete (`unsound`) must be judged by the validate check instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from wc.expand.element_pairs import Candidates, ClothElements, gather, measured_capacity, search
from wc.model.padded_neighbors import NeighborCapacity

RADIUS_SLACK = 1.0e-3  # relative: the grid's distance test is strict


def segment_crosses_triangle(p: Tensor, q: Tensor, a: Tensor, b: Tensor, c: Tensor, eps: float = 1e-12) -> Tensor:
    """(...) bool: the segment p-q (..., 3) meets the triangle a, b, c (..., 3) (Moeller-Trumbore, t in [0, 1]); a
    segment in the triangle's plane does not count (measure zero, as for a ray cast)."""
    e1, e2, d = b - a, c - a, q - p
    h = torch.linalg.cross(d, e2)
    det = (e1 * h).sum(-1)
    ok = det.abs() > eps * (e1.norm(dim=-1) * e2.norm(dim=-1) * d.norm(dim=-1)).clamp_min(1e-30)
    inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
    s = p - a
    u = inv * (s * h).sum(-1)
    r = torch.linalg.cross(s, e1)
    w = inv * (d * r).sum(-1)
    t = inv * (e2 * r).sum(-1)
    return ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= 0) & (t <= 1)


@dataclass
class Crossings:
    """Per episode: involved (B, N) bool rows on a crossing edge or crossed triangle; crossing (B,) bool any crossing;
    unsound (B,) bool the candidate lists were incomplete (judge with wc.validate.self_intersection)."""

    involved: Tensor
    crossing: Tensor
    unsound: Tensor


class CrossingTest:
    """Edge-triangle crossings of the cloth meshes of a batch of states (module docstring). stretch: elements up to
    this times their largest rest size are searched exactly; capacity: candidate slots per edge (`capacity_of`)."""

    def __init__(self, elements: ClothElements, capacity: NeighborCapacity, stretch: float = 1.5) -> None:
        if not stretch >= 1.0:
            raise ValueError(f"crossing test stretch must be >= 1, got {stretch}")
        self.elements, self.capacity, self.stretch = elements, capacity, float(stretch)
        self.radius = stretch * (elements.edge_half_m + elements.face_radius_m) * (1 + RADIUS_SLACK)

    @classmethod
    def capacity_of(cls, elements: ClothElements, states: Tensor, stretch: float = 1.5,
                    headroom: float = 2.0) -> NeighborCapacity:
        """Slots measured on sample states (B, N, 3) x headroom."""
        radius = stretch * (elements.edge_half_m + elements.face_radius_m) * (1 + RADIUS_SLACK)
        return measured_capacity(elements.edge_midpoints(states), elements.edge_mesh, elements.face_centres(states),
                                 elements.face_mesh, elements.meshes, radius, headroom)

    def candidates(self, x: Tensor) -> Candidates:
        el = self.elements
        return search(el.edge_midpoints(x), el.edge_mesh, el.face_centres(x), el.face_mesh, el.meshes, self.radius,
                      self.capacity)

    def __call__(self, x: Tensor) -> Crossings:
        """Crossings of states x (B, N, 3) (non-finite episodes: none found; the finiteness check judges them)."""
        el = self.elements
        bsz, n = x.shape[:2]
        if len(el.edges) == 0:
            false = torch.zeros(bsz, dtype=torch.bool, device=x.device)
            return Crossings(torch.zeros(x.shape[:2], dtype=torch.bool, device=x.device), false, false)
        found = self.candidates(x)
        tri = el.faces[found.other]  # (B, E, K, 3) rows
        ends = el.edges[None, :, None, :].expand(bsz, -1, tri.shape[2], -1)  # (B, E, K, 2)
        adjacent = (tri[..., :, None] == ends[..., None, :]).any(dim=(-1, -2))
        corners = gather(x, tri)  # (B, E, K, 3, 3)
        p, q = gather(x, ends[..., 0]), gather(x, ends[..., 1])
        hit = found.valid & ~adjacent & segment_crosses_triangle(p, q, corners[..., 0, :], corners[..., 1, :],
                                                                  corners[..., 2, :])
        flat = torch.zeros(bsz * n, dtype=x.dtype, device=x.device)
        first = (torch.arange(bsz, device=x.device) * n)
        edge_hit = hit.any(dim=2).to(x.dtype)  # (B, E)
        for end in range(2):
            flat.index_add_(0, (first[:, None] + el.edges[None, :, end]).reshape(-1), edge_hit.reshape(-1))
        face_rows = (first[:, None, None, None] + tri).reshape(-1)
        flat.index_add_(0, face_rows, hit[..., None].expand_as(tri).to(x.dtype).reshape(-1))
        involved = flat.view(bsz, n) > 0
        unsound = found.dropped | el.oversized(x, self.stretch)
        return Crossings(involved, hit.any(dim=(1, 2)), unsound)
