"""A predicted step that cannot make the cloth cross itself: relative motions bounded by the distances between mesh
elements (an option of the expand stage's projection, `expand.untangle: bounded`).

Moving linearly from a state where no cloth edge crosses a non-adjacent triangle, an edge can only come to cross a
triangle after a vertex touched the triangle or an edge touched one of its edges. If every vertex-triangle and
edge-edge pair of non-adjacent elements, d apart at the start, changes its endpoints' relative positions by less
than d (|Δx_i - Δx_j| <= share * d for each vertex i of one element and j of the other), no two points of the pair
come closer than (1 - share) * d on the way: the step is crossing-free. This is the conservative bound of
penetration-free cloth solvers (the "offset geometry" bounds of Chen et al. 2024-25's vertex block descent and OGC),
here on relative motion, so a layer carried along with the one under it (a strap between closing pads) is not held
back. The bounds are enforced on the step's displacements by projection (each violated pair pulled to its bound,
the end whose step departs more from its mesh neighbours' taking more of the correction; Jacobi passes), and where passes are not enough both ends of a still-violated
pair keep the previous state, which always satisfies them. Distances are then measured again at the state reached
and the rest of the step tried (`rounds` times), so elements sliding along each other get further than one bound.
Velocities follow the position corrections (v += Δx / Δt): the pair's relative velocity shrinks, none is invented.
Nothing is bag-specific: every cloth object of the scene. Candidate pairs come from a brute-force distance test
between element bounding spheres per episode, in chunks: cheap for the CPU default's 306-vertex bag, quadratic in
the mesh size.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from wc.validate.self_intersection import unique_edges

CHUNK = 1024  # elements per bounding-sphere distance block (bounds memory: B x CHUNK x elements)


def point_segment_distance(p: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """(M,) distances of points p (M, 3) to segments ab (M, 3)."""
    ab = b - a
    t = (((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-30)).clamp(0.0, 1.0)
    return (p - a - t[:, None] * ab).norm(dim=-1)


def point_triangle_distance(p: Tensor, tri: Tensor) -> Tensor:
    """(M,) distances of points p (M, 3) to triangles tri (M, 3, 3): the plane distance where p projects inside the
    triangle, else the nearest of its three sides."""
    a, b, c = tri.unbind(1)
    normal = torch.linalg.cross(b - a, c - a)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    height = ((p - a) * normal).sum(-1)
    q = p - height[:, None] * normal
    inside = torch.ones_like(height, dtype=torch.bool)
    for u, w in ((a, b), (b, c), (c, a)):  # q on the inner side of each directed side (counter-clockwise about normal)
        inside &= (torch.linalg.cross(w - u, q - u) * normal).sum(-1) >= 0
    sides = torch.stack([point_segment_distance(p, u, w) for u, w in ((a, b), (b, c), (c, a))]).amin(dim=0)
    return torch.where(inside, height.abs(), sides)


def segment_segment_distance(p1: Tensor, q1: Tensor, p2: Tensor, q2: Tensor) -> Tensor:
    """(M,) distances between segments p1q1 and p2q2 (M, 3) (Ericson, Real-Time Collision Detection 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = (d1 * d1).sum(-1).clamp_min(1e-30), (d2 * d2).sum(-1).clamp_min(1e-30)
    b, c, f = (d1 * d2).sum(-1), (d1 * r).sum(-1), (d2 * r).sum(-1)
    denom = a * e - b * b
    s = torch.where(denom > 1e-12 * a * e, ((b * f - c * e) / denom.clamp_min(1e-30)).clamp(0.0, 1.0),
                    torch.zeros_like(a))
    t = (b * s + f) / e
    s = torch.where(t < 0, (-c / a).clamp(0.0, 1.0), torch.where(t > 1, ((b - c) / a).clamp(0.0, 1.0), s))
    t = t.clamp(0.0, 1.0)
    return (p1 + s[:, None] * d1 - p2 - t[:, None] * d2).norm(dim=-1)


def _near_pairs(centre_a: Tensor, radius_a: Tensor, centre_b: Tensor, radius_b: Tensor, reach_a: Tensor,
                reach_b: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(episode, a, b) of elements whose bounding spheres (centres (B, A, 3) / (B, C, 3), radii (B, A) / (B, C))
    come within reach_a + reach_b ((B, A) / (B, C)) of each other."""
    found = []
    for lo in range(0, centre_a.shape[1], CHUNK):
        hi = min(centre_a.shape[1], lo + CHUNK)
        gap = (torch.cdist(centre_a[:, lo:hi], centre_b) - radius_a[:, lo:hi, None] - radius_b[:, None]
               - reach_a[:, lo:hi, None] - reach_b[:, None])
        b, i, k = torch.nonzero(gap < 0, as_tuple=True)
        found.append((b, i + lo, k))
    return tuple(torch.cat(parts) for parts in zip(*found))  # type: ignore[return-value]


class CrossingFreeStep:
    """Bounds a step's relative motions so that the cloth cannot cross itself (module docstring).

    share: the fraction of a pair's distance its ends may move relative to each other per round (< 1); rounds:
    distance measurements (and tries at the rest of the step) at most; passes: Jacobi passes per round; hold:
    the ends of pairs the passes leave violated keep the previous state (False: they are left as they are); then: a
    guard applied to the bounded step after it (`SelfIntersectionGuard`: rollback of what crossings remain).
    """

    def __init__(self, scene, share: float = 0.8, rounds: int = 3, passes: int = 30, hold: bool = True,  # noqa: ANN001
                 then: object | None = None) -> None:
        if not 0 < share < 1 or rounds < 1 or passes < 1:
            raise ValueError(f"need 0 < share < 1, rounds >= 1 and passes >= 1; got {share}, {rounds}, {passes}")
        self.share, self.rounds, self.passes, self.hold, self.then = float(share), rounds, passes, hold, then
        slices = scene.vertex_slices()
        self.meshes = []  # (first row, vertex count, faces (F, 3), edges (E, 2)) in the mesh's own rows
        for name, mesh in scene.objects.items():
            if scene.object_kinds[name] == "cloth":
                faces = np.asarray(mesh.faces, np.int64)
                self.meshes.append((slices[name].start, len(mesh.vertices), torch.as_tensor(faces),
                                    torch.as_tensor(unique_edges(faces).astype(np.int64))))
        self.stats = {"steps": 0, "limited_steps": 0, "limited_pairs": 0, "held_vertex_steps": 0,
                      "max_cut_m": 0.0}

    def bounds(self, y: Tensor, step: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Vertex pairs (episode, row i, row j) (M,) with their bound (M,) [m] at state y (B, N, 3) for a step
        (B, N, 3): the ends of every non-adjacent vertex-triangle and edge-edge pair of cloth whose bound, share x
        the pair's distance, the step could exceed (the two elements' largest vertex moves added)."""
        parts = []
        move = step.norm(dim=-1) / self.share  # (B, N): a pair farther apart than the moves / share is safe
        for start, n, faces, edges in self.meshes:
            f, e = faces.to(y.device) + start, edges.to(y.device) + start
            rows = torch.arange(start, start + n, device=y.device)
            corners = y[:, f]  # (B, F, 3, 3)
            centre = corners.mean(dim=2)
            radius = (corners - centre[:, :, None]).norm(dim=-1).amax(dim=-1)
            reach_f = move[:, f].amax(dim=-1)
            b, i, k = _near_pairs(y[:, rows], torch.zeros_like(move[:, rows]), centre, radius, move[:, rows], reach_f)
            v = rows[i]
            keep = (f[k] != v[:, None]).all(dim=1)
            b, v, k = b[keep], v[keep], k[keep]
            d = point_triangle_distance(y[b, v], y[b[:, None], f[k]])
            near = d < move[b, v] + reach_f[b, k]
            for c in range(3):
                parts.append((b[near], v[near], f[k[near], c], d[near]))
            ends = y[:, e]  # (B, E, 2, 3)
            mid, half = ends.mean(dim=2), (ends[:, :, 1] - ends[:, :, 0]).norm(dim=-1) / 2
            reach_e = move[:, e].amax(dim=-1)
            b, i, k = _near_pairs(mid, half, mid, half, reach_e, reach_e)
            keep = (i < k) & (e[i, 0] != e[k, 0]) & (e[i, 0] != e[k, 1]) & (e[i, 1] != e[k, 0]) & (e[i, 1] != e[k, 1])
            b, i, k = b[keep], i[keep], k[keep]
            d = segment_segment_distance(y[b, e[i, 0]], y[b, e[i, 1]], y[b, e[k, 0]], y[b, e[k, 1]])
            near = d < reach_e[b, i] + reach_e[b, k]
            for s in range(2):
                for t in range(2):
                    parts.append((b[near], e[i[near], s], e[k[near], t], d[near]))
        if not parts:
            empty = torch.zeros(0, dtype=torch.long, device=y.device)
            return empty, empty, empty, y.new_zeros(0)
        b, i, j, d = (torch.cat(p) for p in zip(*parts))
        return b, i, j, self.share * d

    def yield_weights(self, step: Tensor) -> Tensor:
        """(B, N) share of a pair correction each vertex takes: how far its step departs from the mean step of its
        mesh neighbours (a vertex the network moved against its neighbourhood yields first), plus 1 um."""
        total = torch.zeros_like(step)
        count = torch.zeros(step.shape[:2], dtype=step.dtype, device=step.device)
        for start, _, _, edges in self.meshes:
            e = edges.to(step.device) + start
            for a, b in ((e[:, 0], e[:, 1]), (e[:, 1], e[:, 0])):
                total.index_add_(1, a, step[:, b])
                count.index_add_(1, a, torch.ones_like(step[:, b, 0]))
        mean = total / count.clamp_min(1.0)[..., None]
        return torch.where(count > 0, (step - mean).norm(dim=-1), torch.zeros_like(count)) + 1e-6

    def _project(self, step: Tensor, b: Tensor, i: Tensor, j: Tensor, bound: Tensor) -> Tensor:
        """step (B, N, 3) with every pair's relative displacement within its bound (in place, returned)."""
        weight = self.yield_weights(step)
        for _ in range(self.passes):
            rel = step[b, i] - step[b, j]
            length = rel.norm(dim=-1)
            over = length > bound
            if not over.any():
                return step
            bo, io, jo = b[over], i[over], j[over]
            excess = (1.0 - bound[over] / length[over])[:, None] * rel[over]  # the relative move to take back
            wi, wj = weight[bo, io], weight[bo, jo]
            delta, count = torch.zeros_like(step), torch.zeros(step.shape[:2], dtype=step.dtype, device=step.device)
            ones = torch.ones_like(wi)
            delta.index_put_((bo, io), -(wi / (wi + wj))[:, None] * excess, accumulate=True)
            delta.index_put_((bo, jo), (wj / (wi + wj))[:, None] * excess, accumulate=True)
            count.index_put_((bo, io), ones, accumulate=True)
            count.index_put_((bo, jo), ones, accumulate=True)
            step += delta / count.clamp_min(1.0)[..., None]
        if not self.hold:  # the leftovers are `then`'s (expand.untangle: bounded+rollback)
            return step
        held = torch.zeros(step.shape[:2], dtype=torch.bool, device=step.device)
        while True:  # what the passes left: both ends keep the previous state, which satisfies every bound
            over = (step[b, i] - step[b, j]).norm(dim=-1) > bound
            if not over.any():
                self.stats["held_vertex_steps"] += int(held.sum())
                return step
            held[b[over], i[over]] = True
            held[b[over], j[over]] = True
            step[held] = 0.0

    @torch.no_grad()
    def apply(self, x_prev: Tensor, x: Tensor, v: Tensor, dt: float) -> tuple[Tensor, Tensor]:
        """(x, v) (B, N, 3) of a step from the crossing-free x_prev towards x, as far as the bounds allow."""
        if not self.meshes:
            return x, v
        y, target = x_prev.double(), x.double()
        finite = torch.isfinite(target).all(dim=-1).all(dim=-1) & torch.isfinite(y).all(dim=-1).all(dim=-1)
        y = torch.where(finite[:, None, None], y, target)  # a diverged episode is the blow-up check's to reject
        limited = False
        for _ in range(self.rounds):
            step = torch.where(finite[:, None, None], target - y, torch.zeros_like(y))
            b, i, j, bound = self.bounds(y, step)
            free = step.clone()
            step = self._project(step, b, i, j, bound)
            y = y + step
            if torch.equal(step, free):
                break
            limited = True
            self.stats["limited_pairs"] += int(((free[b, i] - free[b, j]).norm(dim=-1) > bound).sum())
        cut = (target - y).norm(dim=-1)
        self.stats["steps"] += 1
        self.stats["limited_steps"] += int(limited)
        if finite.any():
            self.stats["max_cut_m"] = max(self.stats["max_cut_m"], float(cut[finite].max()))
        x_out = y.to(x.dtype)
        v_out = v + (x_out - x) / dt
        return self.then.apply(x_prev, x_out, v_out, dt) if self.then is not None else (x_out, v_out)
