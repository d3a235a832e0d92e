"""Keeping a predicted step from making the cloth cross itself, with fixed pass counts and static shapes (the fast
expansion path; references: wc.expand.crossing_free `CrossingFreeStep`, wc.expand.untangle `SelfIntersectionGuard`).

- `BoundedStep`: every non-adjacent vertex-triangle and edge-edge pair of cloth d apart at the step's start keeps its
  ends' relative displacement within share x d (then no crossing can form on the way); violated pairs are pulled to
  their bound by Jacobi passes, the end whose step departs more from its mesh neighbours' yielding more; distances are
  measured again at the state reached and the rest of the step tried, `rounds` times. Pairs come from the batch's
  grouped BVH (wc.validate.cloth_bvh) within the reach the step's moves could close.
- `Rollback`: the vertices of each crossing edge and crossed triangle - then their mesh neighbours, a ring per round -
  take a shorter step from the previous, crossing-free state (1/2, 1/4, ..., none from round `full_from` on), in
  `rounds` rounds; the crossings left after the last round are the frame's self-intersection verdict.
Both act on every episode of the batch at once and never read a value back to the host.
"""

from __future__ import annotations

import torch
from torch import Tensor

from wc.expand.crossing_free import point_triangle_distance, segment_segment_distance
from wc.expand.cloth_elements import ClothElements, compact, host_checks, spread_unused
from wc.validate.cloth_bvh import ClothBVH


class BoundedStep:
    """Relative motions bounded by element distances (module docstring). share < 1; rounds >= 1; passes >= 1;
    vertex_pairs / edge_pairs: candidate slots per cloth vertex / edge; pair_capacity: near pairs per episode kept
    for the passes on CUDA (the CPU keeps exactly the near pairs)."""

    def __init__(self, elements: ClothElements, share: float, rounds: int, passes: int, vertex_pairs: int,
                 edge_pairs: int, pair_capacity: int) -> None:
        if not 0 < share < 1 or min(rounds, passes, vertex_pairs, edge_pairs, pair_capacity) < 1:
            raise ValueError(f"bounded step: need 0 < share < 1 and rounds, passes, pair slots, pair capacity >= 1; "
                             f"got {share}, {rounds}, {passes}, {vertex_pairs}, {edge_pairs}, {pair_capacity}")
        self.el, self.share, self.rounds, self.passes = elements, float(share), rounds, passes
        self.vertex_slots, self.edge_slots, self.pair_capacity = vertex_pairs, edge_pairs, pair_capacity
        v = elements.vertices
        self.incident = (torch.arange(len(v) + 1, dtype=torch.int32, device=v.device), v.to(torch.int32))  # itself

    def yield_weights(self, step: Tensor) -> Tensor:
        """(B, N) share of a pair correction each vertex takes: how far its step departs from its mesh neighbours'
        mean step, plus 1 um (as CrossingFreeStep.yield_weights)."""
        e = self.el.edges
        total = torch.zeros_like(step)
        count = step.new_zeros(step.shape[:2])
        for a, b in ((e[:, 0], e[:, 1]), (e[:, 1], e[:, 0])):
            total.index_add_(1, a, step[:, b])
            count.index_add_(1, a, torch.ones_like(step[:, b, 0]))
        mean = total / count.clamp_min(1.0)[..., None]
        return torch.where(count > 0, (step - mean).norm(dim=-1), torch.zeros_like(count)) + 1e-6

    def _near(self, slots: Tensor, capacity: int | None, dropped: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(episode, element, partner, valid) (P,) of the filled slots (B, Q, K) (partner -1: empty), compacted."""
        bsz, q, k = slots.shape
        idx, valid, lost = compact(slots >= 0, None if capacity is None else bsz * capacity)
        dropped += lost.to(dropped.dtype)
        return idx // (q * k), (idx // k) % q, slots.reshape(-1)[idx].clamp_min(0).long(), valid

    def pairs(self, bvh: ClothBVH, y: Tensor, step: Tensor, dropped: Tensor
              ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Vertex pairs (episode, I, J, bound [m], valid) (M,) whose bound the step could exceed; dropped (B,) int32
        set where a candidate list overflowed."""
        el, bsz = self.el, y.shape[0]
        move = step.norm(dim=-1) / self.share  # (B, N): a pair farther apart than its ends' moves / share is safe
        bvh.refit(y)
        vt = torch.empty(bsz, len(el.vertices), self.vertex_slots, dtype=torch.int32, device=y.device)
        ee = torch.empty(bsz, len(el.edges), self.edge_slots, dtype=torch.int32, device=y.device)
        bvh.vertex_face_pairs(y, move[:, el.vertices], move[:, el.faces].amax(dim=-1), self.incident, vt, dropped)
        bvh.edge_edge_pairs(y, move[:, el.edges].amax(dim=-1), ee, dropped)
        capacity = None if host_checks(y) else self.pair_capacity
        lost = dropped.new_zeros(())
        b, vi, f, valid_vt = self._near(vt, capacity, lost)
        tri, row = el.faces[f], el.vertices[vi]
        d_vt = point_triangle_distance(y[b, row], y[b[:, None], tri])
        b2, ei, ki, valid_ee = self._near(ee, capacity, lost)
        own, other = el.edges[ei], el.edges[ki]
        d_ee = segment_segment_distance(y[b2, own[:, 0]], y[b2, own[:, 1]], y[b2, other[:, 0]], y[b2, other[:, 1]])
        dropped[0] += lost  # capacity overflow: counted once per batch (which episode lost a pair is not kept)
        parts = [(b, row, tri[:, c], d_vt, valid_vt) for c in range(3)]
        parts += [(b2, own[:, s], other[:, t], d_ee, valid_ee) for s in range(2) for t in range(2)]
        episode, i, j, d, valid = (torch.cat([p[k] for p in parts]) for k in range(5))
        return episode, i, j, self.share * d, valid

    def _project(self, step: Tensor, episode: Tensor, i: Tensor, j: Tensor, bound: Tensor, valid: Tensor
                 ) -> tuple[Tensor, Tensor]:
        """step with every valid pair's relative displacement pulled within its bound (Jacobi passes; in place), and
        the count of pairs over their bound at the start."""
        bsz, n = step.shape[:2]
        flat = step.view(-1, 3)
        fi, fj = (spread_unused(episode * n + k, valid, bsz * n) for k in (i, j))
        weight = self.yield_weights(step).view(-1)
        share_i = (weight[fi] / (weight[fi] + weight[fj]))[:, None]
        limited = None
        for _ in range(self.passes):
            rel = flat[fi] - flat[fj]
            length = rel.norm(dim=-1)
            over = valid & (length > bound)
            if limited is None:
                limited = over.sum()
            if host_checks(step) and not bool(over.any()):
                break
            excess = torch.where(over[:, None], (1.0 - bound / length.clamp_min(1e-30))[:, None] * rel,
                                 torch.zeros_like(rel))
            ones = over.to(step.dtype)
            delta = torch.zeros_like(flat).index_add_(0, fi, -share_i * excess).index_add_(0, fj, (1 - share_i) * excess)
            count = flat.new_zeros(len(flat)).index_add_(0, fi, ones).index_add_(0, fj, ones)
            flat += delta / count.clamp_min(1.0)[:, None]
        return step, limited if limited is not None else step.new_zeros((), dtype=torch.long)

    @torch.no_grad()
    def apply(self, bvh: ClothBVH, x_prev: Tensor, x: Tensor, v: Tensor, dt: float, stats: dict[str, Tensor]
              ) -> tuple[Tensor, Tensor]:
        """(x, v) (B, N, 3) of the step from x_prev towards x as far as the bounds allow; counts into stats."""
        finite = torch.isfinite(x).all(dim=-1).all(dim=-1) & torch.isfinite(x_prev).all(dim=-1).all(dim=-1)
        y = torch.where(finite[:, None, None], x_prev, x)  # a diverged episode is the finiteness check's to reject
        for _ in range(self.rounds):
            step = torch.where(finite[:, None, None], x - y, torch.zeros_like(y)).contiguous()
            dropped = torch.zeros(y.shape[0], dtype=torch.int32, device=y.device)
            episode, i, j, bound, valid = self.pairs(bvh, y, step, dropped)
            step, limited = self._project(step, episode, i, j, bound, valid)
            stats["pairs_dropped"] += dropped.sum()
            stats["limited_pairs"] += limited
            y = y + step
            if host_checks(y) and not int(limited):
                break
        cut = torch.where(finite[:, None], (x - y).norm(dim=-1), torch.zeros_like(y[..., 0]))
        torch.maximum(stats["max_cut_m"], cut.amax(), out=stats["max_cut_m"])
        return y, v + (y - x) / dt


class Rollback:
    """Self-crossings a step leaves rolled back towards the previous state (module docstring). rounds >= 1 rounds in
    all; from round full_from on a rolled-back vertex keeps its previous state."""

    def __init__(self, elements: ClothElements, rounds: int, full_from: int) -> None:
        if rounds < 1 or full_from < 1:
            raise ValueError(f"rollback: need rounds >= 1 and full_from >= 1, got {rounds}, {full_from}")
        self.el, self.rounds, self.full_from = elements, rounds, full_from

    def grow(self, mask: Tensor) -> Tensor:
        """mask (B, N) widened by one ring of cloth mesh neighbours."""
        e = self.el.edges
        m = mask.to(torch.float32)
        acc = torch.zeros_like(m)
        acc.index_add_(1, e[:, 0], m[:, e[:, 1]])
        acc.index_add_(1, e[:, 1], m[:, e[:, 0]])
        return mask | (acc > 0)

    def crossings(self, bvh: ClothBVH, x: Tensor) -> tuple[Tensor, Tensor]:
        """(involved (B, N) bool, crossing (B,) bool) of states x (the trees refitted to them)."""
        bvh.refit(x)
        involved = torch.zeros(x.shape[:2], dtype=torch.int32, device=x.device)
        crossing = torch.zeros(x.shape[0], dtype=torch.int32, device=x.device)
        hit = torch.empty(x.shape[0], len(self.el.edges), dtype=torch.int32, device=x.device)
        bvh.crossings(x, involved, crossing, hit)
        return involved > 0, crossing > 0

    @torch.no_grad()
    def apply(self, bvh: ClothBVH, x_prev: Tensor, x: Tensor, v: Tensor, stats: dict[str, Tensor]
              ) -> tuple[Tensor, Tensor, Tensor]:
        """(x, v, crossing (B,) bool: a crossing is left after the last round)."""
        involved, crossing = self.crossings(bvh, x)
        stats["steps_with_crossings"] += crossing.sum()
        rolled = torch.zeros_like(involved)
        x_out, v_out = x.clone(), v.clone()
        for r in range(1, self.rounds + 1):
            if host_checks(x) and not bool(crossing.any()):
                break
            grow = involved if r == 1 else self.grow(rolled | involved)
            rolled = torch.where(crossing[:, None], rolled | grow, rolled)
            a = 0.5 ** r if r < self.full_from else 0.0
            moved = (rolled & crossing[:, None])[..., None]
            x_out = torch.where(moved, x_prev + a * (x - x_prev), x_out)
            v_out = torch.where(moved, a * v, v_out)
            involved, now = self.crossings(bvh, x_out)
            crossing = crossing & now
        stats["rolled_back_vertex_steps"] += rolled.sum()
        stats["unresolved_steps"] += crossing.sum()
        return x_out, v_out, crossing
