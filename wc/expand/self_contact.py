"""Cloth self-contact in the generation path: every cloth vertex kept a gap from the triangles of its own mesh, on
the side it came from (an option of the expand stage's joint projection).

A flat bag's two walls, or a strap pinched between pads, lie one contact gap apart in the source simulation
(Newton's self-contact, `sim.self_contact_gap_m`). A learnt step that is off by less than that gap moves one layer
through the other, and the validate stage rejects the episode (`self_intersection`). Here, as in position-based
cloth (Müller et al. 2007, Bridson et al. 2002), each vertex-triangle pair closer than `gap_m` - skipping the
triangles within `filter_rings` mesh rings of the vertex, as Newton's filter does - is pushed apart along the
triangle's normal until the vertex is `gap_m` from the triangle's plane on the side it was on at the previous
state, the move split between the vertex and the triangle's corners by inverse mass and barycentric weight
(pinned vertices do not move). Corrections of one pass are averaged per vertex (Jacobi). Nothing is bag-specific:
every cloth object of the scene. Candidate pairs come from a brute-force centroid distance test per episode, in
chunks of vertices: cheap for the CPU default's 306-vertex bag, quadratic in the mesh size.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from wc.expand.cloth_elements import spread_unused
from wc.validate.self_intersection import unique_edges

CHUNK = 1024  # vertices per centroid-distance block (bounds memory: B x CHUNK x F floats)


def ring_pairs(n: int, edges: np.ndarray, rings: int) -> np.ndarray:
    """Sorted keys i * n + j of the vertex pairs (i, j) at most `rings` mesh edges apart, (i, i) included."""
    near = [{i} for i in range(n)]
    neighbours = [set() for _ in range(n)]
    for a, b in np.asarray(edges):
        neighbours[a].add(int(b))
        neighbours[b].add(int(a))
    for _ in range(rings):
        near = [s.union(*(neighbours[j] for j in s)) for s in near]
    return np.sort(np.concatenate([i * n + np.fromiter(s, np.int64) for i, s in enumerate(near)]))


class SelfContactSeparation:
    """Vertex-triangle separation of a scene's cloth (module docstring). gap_m: the kept distance [m]; filter_rings:
    triangles with a corner this many rings from the vertex, or closer, are skipped; margin_m: extra search
    distance, so that pairs found before the projection's passes still cover the vertices' moves during them."""

    def __init__(self, scene, gap_m: float, filter_rings: int = 1, margin_m: float = 0.002) -> None:  # noqa: ANN001
        if not gap_m > 0 or filter_rings < 0 or margin_m < 0:
            raise ValueError(f"need gap_m > 0, filter_rings >= 0, margin_m >= 0; got {gap_m}, {filter_rings}, {margin_m}")
        self.gap_m, self.margin_m = float(gap_m), float(margin_m)
        slices = scene.vertex_slices()
        self.meshes = []  # (first row, vertex count, faces (F, 3) local, filtered pair keys)
        for name, mesh in scene.objects.items():
            if scene.object_kinds[name] != "cloth":
                continue
            faces = np.asarray(mesh.faces, np.int64)
            n = len(mesh.vertices)
            self.meshes.append((slices[name].start, n, faces, ring_pairs(n, unique_edges(faces), filter_rings)))

    def pairs(self, x: Tensor) -> list[tuple[Tensor, Tensor, Tensor]]:
        """Per cloth mesh: candidate (episode, vertex row, face rows (K, 3)) of x (B, N, 3): vertices within a
        triangle's bounding radius + gap + margin of its centroid, filtered triangles left out."""
        out = []
        for start, n, faces, skip in self.meshes:
            f = torch.as_tensor(faces, device=x.device)
            corners = x[:, start + f]  # (B, F, 3, 3)
            centre = corners.mean(dim=2)
            reach = (corners - centre[:, :, None]).norm(dim=-1).amax(dim=-1) + self.gap_m + self.margin_m  # (B, F)
            skip_t = torch.as_tensor(skip, device=x.device)
            found = []
            for lo in range(0, n, CHUNK):
                pts = x[:, start + lo:start + min(n, lo + CHUNK)]
                b, i, k = torch.nonzero(torch.cdist(pts, centre) < reach[:, None], as_tuple=True)
                i = i + lo
                keys = i[:, None] * n + f[k]  # (M, 3): vertex paired with each corner
                keep = ~torch.isin(keys, skip_t).any(dim=1)
                found.append((b[keep], i[keep], k[keep]))
            b, i, k = (torch.cat(parts) for parts in zip(*found))
            out.append((b, start + i, start + f[k]))
        return out

    def separate(self, x_prev: Tensor, x: Tensor, pairs: list[tuple[Tensor, Tensor, Tensor]], inv_mass: Tensor
                 ) -> tuple[Tensor, Tensor]:
        """One Jacobi pass: x (B, N, 3) with its pairs (from `pairs`) pushed gap_m apart, in place; returns x and the
        largest remaining shortfall [m] per episode (B,) before the pass."""
        shortfall = x.new_zeros(x.shape[0])
        for b, i, tri in pairs:
            if len(b):
                gap = separate_pairs(x_prev, x, b, i, tri, torch.ones_like(b, dtype=torch.bool), inv_mass, self.gap_m)
                shortfall = torch.maximum(shortfall, gap)
        return x, shortfall


def separate_pairs(x_prev: Tensor, x: Tensor, b: Tensor, row: Tensor, tri: Tensor, valid: Tensor, inv_mass: Tensor,
                   gap_m: float) -> Tensor:
    """One Jacobi pass over vertex-triangle pairs (M,): a cloth vertex (episode b, row) closer than gap_m to the plane
    of a triangle (rows tri (M, 3)), over the triangle, is pushed apart along its normal to gap_m on the side it was
    on at x_prev, the move split by inverse mass and barycentric weight, corrections averaged per vertex; x (B, N, 3)
    in place. Pairs with valid False count for nothing (static shapes, no host sync). Returns the largest shortfall
    [m] per episode (B,) before the pass."""
    n = x.shape[1]
    p, q = x[b[:, None], tri], x[b, row]  # (M, 3, 3), (M, 3)
    normal = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    d = ((q - p[:, 0]) * normal).sum(-1)
    pp, qp = x_prev[b[:, None], tri], x_prev[b, row]
    n_prev = torch.linalg.cross(pp[:, 1] - pp[:, 0], pp[:, 2] - pp[:, 0])
    side = torch.where(((qp - pp[:, 0]) * n_prev).sum(-1) >= 0, 1.0, -1.0).to(x.dtype)
    w = barycentric(q - d[:, None] * normal, p)  # (M, 3) of the point's projection on the plane
    inside = (w >= -1e-6).all(dim=-1) & valid
    gap = torch.nan_to_num(torch.where(inside, (gap_m - side * d).clamp_min(0.0), torch.zeros_like(d)))
    shortfall = x.new_zeros(x.shape[0]).scatter_reduce(0, spread_unused(b, valid, x.shape[0]), gap, "amax")
    wq, wt = inv_mass[b, row], inv_mass[b[:, None], tri] * w  # (M,), (M, 3)
    total = (wq + (wt * w).sum(-1)).clamp_min(1e-12)
    move = (gap * side / total)[:, None] * normal  # along the normal, towards the vertex's side
    active = (gap > 0).to(x.dtype)
    flat, count = torch.zeros_like(x).view(-1, 3), x.new_zeros(x.shape[0] * n)
    rows = len(flat)
    at = spread_unused(b * n + row, valid, rows)
    flat.index_add_(0, at, wq[:, None] * move)
    count.index_add_(0, at, active * (wq > 0))
    for c in range(3):
        at = spread_unused(b * n + tri[:, c], valid, rows)
        flat.index_add_(0, at, -wt[:, c, None] * move)
        count.index_add_(0, at, active * (wt[:, c] > 0))
    x += (flat / count.clamp_min(1.0)[:, None]).view_as(x)
    return shortfall


def barycentric(point: Tensor, tri: Tensor) -> Tensor:
    """Barycentric coordinates (M, 3) of points (M, 3) in the planes of triangles (M, 3, 3)."""
    v0, v1, v2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], point - tri[:, 0]
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = (d00 * d11 - d01 * d01).clamp_min(1e-20)
    b1, b2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    return torch.stack([1.0 - b1 - b2, b1, b2], dim=-1)
