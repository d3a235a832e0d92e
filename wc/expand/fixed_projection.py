"""The per-step projection of the fast expansion path: the joint projection of wc.expand.constraints (cloth edge
limits, contacts with the scene's bodies, cloth self-contact) and the untangling of wc.expand.crossing_free /
wc.expand.untangle, with fixed iteration counts, static shapes and every statistic kept on the device, so that a whole
predicted frame can be captured as one CUDA graph and no step waits for the host.

Per step, from the previous state x_prev and the network's prediction (x, v):
1. `iterations` passes of: edges (Gauss-Seidel by colour), the push out of the bodies (wc.expand.body_contacts), the
   self-contact separation (wc.expand.self_contact) of vertex-triangle pairs found once at x (grouped BVH,
   wc.validate.cloth_bvh);
   then `final_edge_passes` edge passes. Velocities follow the edge corrections; a pushed vertex loses its velocity
   into the surface (as the reference).
2. The bounded step (wc.expand.fixed_untangle.BoundedStep), then the rollback of the crossings it left (`Rollback`),
   whose last crossing test is the frame's self-intersection verdict (wc.expand.frame_checks).
Where the reference loop stops once everything holds within 0.1 mm, this one runs its passes: extra passes over
satisfied constraints change nothing. Nothing is bag-specific: every cloth object and body of the scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from wc.expand.body_contacts import DeviceBodies, push_out
from wc.expand.constraints import edge_colours, edge_pass
from wc.expand.cloth_elements import ClothElements, compact, host_checks
from wc.expand.fixed_untangle import BoundedStep, Rollback
from wc.expand.self_contact import ring_pairs, separate_pairs
from wc.validate.cloth_bvh import ClothBVH
from wc.validate.self_intersection import unique_edges

SETTLED_M = 1.0e-6  # CPU: a joint pass that moves no vertex further than this ends the loop
STAT_SUMS = ("steps", "limited_pairs", "steps_with_crossings", "rolled_back_vertex_steps", "unresolved_steps",
             "pairs_dropped", "self_contact_pairs")
STAT_MAXIMA = ("max_strain_before", "max_strain_after", "max_strain_final", "max_depth_before_m", "max_depth_after_m",
               "max_cut_m")  # after: the joint projection's (as the reference reports); final: after the untangling


@dataclass(frozen=True)
class FixedProjectionConfig:
    """Pass counts and capacities of the fixed projection (the expand params' `fast_*` keys)."""

    edge_ratio: tuple[float, float]
    iterations: int
    final_edge_passes: int
    self_contact_gap_m: float | None  # None: no self-contact separation
    self_contact_rings: int
    untangle_share: float
    bounded_rounds: int  # 0: no bounded step
    bounded_passes: int
    rollback_rounds: int  # 0: no rollback (crossings are still tested for the check)
    rollback_full_from: int
    vertex_pairs: int  # candidate triangles per cloth vertex (self-contact, bounded step)
    edge_pairs: int  # candidate edges per cloth edge (bounded step)
    pair_capacity: int  # bounded step: near pairs per episode kept for the passes on CUDA (the CPU keeps exactly those)
    self_contact_capacity: int = 256  # self-contact pairs per episode kept on CUDA
    self_contact_margin_m: float = 0.002


def ring_skip(elements: ClothElements, scene, rings: int) -> tuple[Tensor, Tensor]:  # noqa: ANN001
    """CSR (start (V + 1,), rows (S,)) int32 of the rows within `rings` mesh edges of each cloth vertex (itself
    included): triangles with a corner there are not its self-contact partners (Newton's filter)."""
    slices = scene.vertex_slices()
    counts, rows = [], []
    for name, mesh in scene.objects.items():
        if scene.object_kinds[name] != "cloth":
            continue
        n = len(mesh.vertices)
        keys = ring_pairs(n, unique_edges(mesh.faces), rings)
        counts.append(np.bincount(keys // n, minlength=n))
        rows.append(slices[name].start + keys % n)
    counts_all = np.concatenate(counts) if counts else np.zeros(0, np.int64)
    start = np.concatenate([[0], np.cumsum(counts_all)]).astype(np.int32)
    flat = np.concatenate(rows).astype(np.int32) if rows else np.zeros(0, np.int32)
    device = elements.vertices.device
    return torch.as_tensor(start, device=device), torch.as_tensor(flat, device=device)


class FixedStepProjection:
    """The fast path's per-step projection of a scene's cloth for a batch of B episodes (module docstring)."""

    def __init__(self, scene, cfg: FixedProjectionConfig, device: torch.device) -> None:  # noqa: ANN001
        lo, hi = cfg.edge_ratio
        if not 0 < lo <= 1 <= hi or cfg.iterations < 1 or cfg.final_edge_passes < 0:
            raise ValueError(f"fixed projection: need 0 < min <= 1 <= max edge ratio, iterations >= 1, final edge "
                             f"passes >= 0; got {cfg.edge_ratio}, {cfg.iterations}, {cfg.final_edge_passes}")
        self.cfg, self.device = cfg, device
        self.bodies = DeviceBodies(scene, device)
        self.elements = ClothElements.of_scene(scene).to(device)
        edges = self.elements.edges.cpu().numpy()
        rest = np.concatenate([m.vertices for m in scene.objects.values()]).astype(np.float64)
        length = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=-1)
        self.rest_length = torch.as_tensor(length, dtype=torch.float32, device=device)
        self.lo, self.hi = lo * self.rest_length, hi * self.rest_length
        e = self.elements.edges
        self.colours = [(e[c, 0], e[c, 1], torch.as_tensor(c, device=device)) for c in edge_colours(edges)]
        self.skip = ring_skip(self.elements, scene, cfg.self_contact_rings) if cfg.self_contact_gap_m else None
        self.bounded = (BoundedStep(self.elements, cfg.untangle_share, cfg.bounded_rounds, cfg.bounded_passes,
                                    cfg.vertex_pairs, cfg.edge_pairs, cfg.pair_capacity) if cfg.bounded_rounds else None)
        self.rollback = Rollback(self.elements, max(1, cfg.rollback_rounds), max(1, cfg.rollback_full_from))
        self.bvh: ClothBVH | None = None
        self.stats = self.zero_stats()
        self._iteration, self._edge_pass = self._one_iteration, edge_pass
        self.compiled = False  # compile_passes was called

    def zero_stats(self) -> dict[str, Tensor]:
        return {k: torch.zeros((), dtype=torch.float32 if k.startswith("max") else torch.long, device=self.device)
                for k in (*STAT_SUMS, *STAT_MAXIMA)}

    def reset_stats(self) -> None:
        """Counters back to zero, in place (a captured graph keeps writing into the same tensors)."""
        for v in self.stats.values():
            v.zero_()

    def read_stats(self) -> dict[str, float]:
        """The counters on the host (one sync)."""
        return {k: float(v) for k, v in self.stats.items()}

    def prepare(self, x: Tensor) -> None:
        """The batch's BVH (re)built on states x (B, N, 3): once before capture, and when slots take new episodes."""
        el = self.elements
        if self.bvh is None or self.bvh.batch != x.shape[0]:
            self.bvh = ClothBVH(x.float(), el.faces, el.face_mesh, el.edges, el.edge_mesh, el.vertices, el.vertex_mesh,
                                el.meshes)
        else:
            self.bvh.rebuild(x.float())

    def edge_violation(self, x: Tensor) -> Tensor:
        """(B, E) distance [m] of each cloth edge's length outside its [lo, hi] (0 inside)."""
        e = self.elements.edges
        length = (x[:, e[:, 1]] - x[:, e[:, 0]]).norm(dim=-1)
        return torch.nan_to_num(torch.maximum(self.lo - length, length - self.hi).clamp_min(0.0))

    def strain(self, x: Tensor) -> Tensor:
        """(B,) largest |length / rest - 1| over the cloth edges."""
        e = self.elements.edges
        if len(e) == 0:
            return x.new_zeros(x.shape[0])
        return ((x[:, e[:, 1]] - x[:, e[:, 0]]).norm(dim=-1) / self.rest_length - 1.0).abs().amax(dim=-1)

    def _keep_max(self, key: str, values: Tensor) -> None:
        """stats[key] = max(stats[key], finite values), in place (a captured graph keeps its tensors)."""
        torch.maximum(self.stats[key], torch.nan_to_num(values, nan=0.0, posinf=0.0).amax(), out=self.stats[key])

    def _self_contact_pairs(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(episode, vertex row, triangle rows (M, 3), valid) of the cloth vertices within the gap (+ margin) of a
        triangle of their mesh outside their filter rings, compacted."""
        el, cfg = self.elements, self.cfg
        bsz = x.shape[0]
        reach = torch.full((bsz, len(el.vertices)), cfg.self_contact_gap_m + cfg.self_contact_margin_m,
                           dtype=torch.float32, device=x.device)
        slots = torch.empty(bsz, len(el.vertices), cfg.vertex_pairs, dtype=torch.int32, device=x.device)
        dropped = torch.zeros(bsz, dtype=torch.int32, device=x.device)
        self.bvh.refit(x)
        self.bvh.vertex_face_pairs(x, reach, torch.zeros(bsz, len(el.faces), device=x.device), self.skip, slots,
                                   dropped)
        q, k = slots.shape[1:]
        idx, valid, lost = compact(slots >= 0, None if host_checks(x) else bsz * cfg.self_contact_capacity)
        self.stats["pairs_dropped"] += dropped.sum() + lost
        self.stats["self_contact_pairs"] += valid.sum()
        b, vi = idx // (q * k), (idx // k) % q
        return b, el.vertices[vi], el.faces[slots.reshape(-1)[idx].clamp_min(0).long()], valid

    def _one_iteration(self, x_prev: Tensor, out: Tensor, inv_mass: Tensor, edge_shift: Tensor, pushed: Tensor,
                       normal: Tensor, bodies: list, pairs: tuple[Tensor, ...] | None) -> None:
        """One joint pass, in place on out, edge_shift, pushed and normal: edges, the push out of the bodies, the
        self-contact separation."""
        cloth = self.bodies.cloth
        self._edge_pass(out, inv_mass, self.colours, self.lo, self.hi, edge_shift)
        if len(cloth):
            moved, hit = push_out(out[:, cloth], bodies)
            delta = moved - out[:, cloth]
            out[:, cloth] = moved
            pushed[:, cloth] |= hit
            normal[:, cloth] = torch.where(hit[..., None], delta / delta.norm(dim=-1, keepdim=True).clamp_min(1e-12),
                                           normal[:, cloth])
        if pairs is not None:
            separate_pairs(x_prev, out, *pairs, inv_mass, self.cfg.self_contact_gap_m)

    def compile_passes(self, backend: str = "inductor") -> None:
        """The joint pass and the edge pass through torch.compile (fullgraph, static shapes: once per batch size):
        Inductor fuses their many small kernels; the results are the same passes'. For the static path (CUDA)."""
        self._iteration = torch.compile(self._one_iteration, fullgraph=True, dynamic=False, backend=backend)
        self._edge_pass = torch.compile(edge_pass, fullgraph=True, dynamic=False, backend=backend)
        self.compiled = True

    @torch.no_grad()
    def joint(self, x_prev: Tensor, x: Tensor, v: Tensor, link_poses: Tensor, dt: float) -> tuple[Tensor, Tensor]:
        """Part 1 (module docstring): edges, contacts and self-contact of a predicted step x, v (B, N, 3) from x_prev
        under link poses (B, L, 7) at the step's end."""
        if self.bvh is None:
            raise RuntimeError("fixed projection: call prepare(x) with the batch's states first")
        cfg, s = self.cfg, self.stats
        bodies = self.bodies.pose(link_poses, x)
        self._keep_max("max_strain_before", self.strain(x))
        self._keep_max("max_depth_before_m", self.bodies.depth(x, bodies))
        inv_mass = torch.ones(x.shape[:2], dtype=x.dtype, device=x.device)
        out = x.clone()
        edge_shift = torch.zeros_like(x)
        pushed = torch.zeros(x.shape[:2], dtype=torch.bool, device=x.device)
        normal = torch.zeros_like(x)
        pairs = self._self_contact_pairs(x) if self.skip is not None else None
        for _ in range(cfg.iterations):
            before = out.clone() if host_checks(x) else None
            self._iteration(x_prev, out, inv_mass, edge_shift, pushed, normal, bodies, pairs)
            if before is not None and not bool((torch.nan_to_num(out - before).abs() > SETTLED_M).any()):
                break  # the CPU stops once a pass moves nothing; CUDA runs its passes (a captured graph)
        for _ in range(cfg.final_edge_passes):
            if host_checks(x) and not bool((self.edge_violation(out) > SETTLED_M).any()):
                break
            self._edge_pass(out, inv_mass, self.colours, self.lo, self.hi, edge_shift)
        v_out = v + edge_shift / dt
        inward = (v_out * normal).sum(-1, keepdim=True).clamp_max(0.0)
        s["steps"] += 1
        self._keep_max("max_strain_after", self.strain(out))
        return out, torch.where(pushed[..., None], v_out - inward * normal, v_out)

    @torch.no_grad()
    def untangle(self, x_prev: Tensor, x: Tensor, v: Tensor, dt: float) -> tuple[Tensor, Tensor, Tensor]:
        """Part 2: the bounded step from x_prev towards the jointly projected x, v, then the rollback; also the
        crossing (B,) bool a rollback could not undo (the frame fails the self-intersection check)."""
        if self.bounded is not None:
            x, v = self.bounded.apply(self.bvh, x_prev, x, v, dt, self.stats)
        if self.cfg.rollback_rounds:
            x, v, crossing = self.rollback.apply(self.bvh, x_prev, x, v, self.stats)
        else:
            crossing = self.rollback.crossings(self.bvh, x)[1]
        self._keep_max("max_strain_final", self.strain(x))
        return x, v, crossing

    def project(self, x_prev: Tensor, x: Tensor, v: Tensor, link_poses: Tensor, dt: float
                ) -> tuple[Tensor, Tensor, Tensor]:
        """`joint` then `untangle`: projected (x, v) (B, N, 3) and the crossing flags (B,)."""
        x, v = self.joint(x_prev, x, v, link_poses, dt)
        return self.untangle(x_prev, x, v, dt)
