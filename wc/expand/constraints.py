"""One constraint projection per predicted step: cloth edge lengths and contacts enforced together.

A learnt step can stretch the cloth and push it into the table, a robot box or a rigid object. Projecting the
edges and then the contacts in turn (or the reverse) lets each undo the other; here both run in one loop until
both hold within tolerance:
- edges, Gauss-Seidel by colour: the rest edges are coloured so that no two edges of a colour share a vertex, and
  each colour moves both ends of its violating edges to the nearest bound of [min_ratio, max_ratio] x rest length,
  split by inverse mass (pinned vertices do not move). Gauss-Seidel converges on chains where averaged Jacobi
  corrections do not (../shared/reference/learned-simulators.md);
- contacts: vertices inside a body go to the surface of the union of the bodies (`ContactProjection.push_out`);
- optionally self-contact: cloth vertices kept a gap from their own mesh's triangles (wc.expand.self_contact).
Where the loop ends unconverged (contacts, self-contact and edges fighting, e.g. a strap squeezed between closing
pads), `final_edge_passes` more edge-only passes can follow: a strained edge is what tears a generated bag
(validate's blow_up), while a shallow penetration left behind stays within the penetration check's tolerance.
Velocities follow the edge corrections (v += Δx_edge / Δt, as the projection stage's V = ΔX / Δt), but a contact
correction injects none: the push moves the vertex, and only its velocity into the surface is removed (a
self-contact correction moves positions only).

Nothing here is bag-specific: edges of every cloth object of the scene, whatever bodies it has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from wc.expand.carry import PadCarry
from wc.expand.contact import Bodies, ContactProjection
from wc.expand.crossing_free import CrossingFreeStep
from wc.expand.self_contact import SelfContactSeparation
from wc.expand.untangle import SelfIntersectionGuard
from wc.validate.self_intersection import unique_edges


def edge_colours(edges: np.ndarray) -> list[np.ndarray]:
    """Edge index sets (E,) of a greedy colouring: no two edges of one set share a vertex."""
    used: dict[int, set[int]] = {}
    colour_of = np.empty(len(edges), np.int64)
    for e, (i, j) in enumerate(np.asarray(edges)):
        taken = used.setdefault(int(i), set()) | used.setdefault(int(j), set())
        c = next(k for k in range(len(taken) + 1) if k not in taken)
        colour_of[e] = c
        used[int(i)].add(c)
        used[int(j)].add(c)
    return [np.flatnonzero(colour_of == c) for c in range(int(colour_of.max(initial=-1)) + 1)]


def edge_pass(x: Tensor, inv_mass: Tensor, colours: list[tuple[Tensor, Tensor, Tensor]], lo: Tensor, hi: Tensor,
              shift: Tensor) -> Tensor:
    """One Gauss-Seidel pass over the edge colours (each (i, j, edge index)): both ends of every edge outside its
    [lo, hi] length move to the nearest bound, split by inverse mass; x (B, N, 3) corrected in place and returned,
    its move added to shift (B, N, 3). No host sync."""
    before = x.clone()
    for i, j, e in colours:
        d = x[:, j] - x[:, i]
        length = d.norm(dim=-1).clamp_min(1e-12)
        target = torch.minimum(torch.maximum(length, lo[e]), hi[e])
        wi, wj = inv_mass[:, i], inv_mass[:, j]
        share = (wi + wj).clamp_min(1e-12)
        step = ((length - target) / (length * share))[..., None] * d  # total move, split by inverse mass
        x[:, i] += wi[..., None] * step
        x[:, j] -= wj[..., None] * step
    shift += x - before
    return x


@dataclass(frozen=True)
class ProjectionReport:
    """Per episode (B,): edge strain (max |length / rest - 1|) and deepest penetration [m] before and after, and
    whether both hold within tolerance after `iterations` loop passes."""

    strain_before: np.ndarray
    strain_after: np.ndarray
    depth_before: np.ndarray
    depth_after: np.ndarray
    converged: np.ndarray
    iterations: int


class ConstraintProjection:
    """Edge limits and contacts of a scene's cloth, projected together (module doc).

    edge_ratio: (min, max) length / rest length; iterations: loop passes at most; tolerance_m: allowed edge
    overshoot [m] and penetration depth [m] when the loop stops early; final_edge_passes: edge-only passes at most
    after a loop that ended with edges still violated (0: none).
    """

    def __init__(self, scene, edge_ratio: tuple[float, float] = (0.9, 1.1), iterations: int = 50,  # noqa: ANN001
                 tolerance_m: float = 1e-4, self_contact: SelfContactSeparation | None = None,
                 final_edge_passes: int = 0) -> None:
        lo, hi = edge_ratio
        if not 0 < lo <= 1 <= hi:
            raise ValueError(f"edge_ratio must satisfy 0 < min <= 1 <= max, got {edge_ratio}")
        if iterations < 1 or not tolerance_m > 0 or final_edge_passes < 0:
            raise ValueError(f"need iterations >= 1, tolerance_m > 0 and final_edge_passes >= 0, got {iterations}, "
                             f"{tolerance_m}, {final_edge_passes}")
        self.contacts = ContactProjection(scene)
        self.iterations, self.tolerance_m, self.self_contact = iterations, tolerance_m, self_contact
        self.final_edge_passes = final_edge_passes
        slices = scene.vertex_slices()
        edges = [unique_edges(m.faces).astype(np.int64) + slices[n].start for n, m in scene.objects.items()
                 if scene.object_kinds[n] == "cloth"]
        self.edges = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
        rest = np.concatenate([m.vertices for m in scene.objects.values()])
        self.rest_length = np.linalg.norm(rest[self.edges[:, 1]] - rest[self.edges[:, 0]], axis=-1)
        self.bounds = (lo * self.rest_length, hi * self.rest_length)
        self.colours = edge_colours(self.edges)

    def _tensors(self, like: Tensor) -> tuple[list[tuple[Tensor, Tensor, Tensor]], Tensor, Tensor, Tensor]:
        def t(a: np.ndarray, dtype: torch.dtype | None = None) -> Tensor:
            return torch.as_tensor(a, dtype=dtype or like.dtype, device=like.device)

        edges = t(self.edges, torch.long)
        colours = [(edges[c, 0], edges[c, 1], t(c, torch.long)) for c in map(np.asarray, self.colours)]
        return colours, t(self.bounds[0]), t(self.bounds[1]), t(self.rest_length)

    def strain(self, x: Tensor) -> Tensor:
        """(B,) max |length / rest - 1| over the cloth edges of x (B, N, 3)."""
        if len(self.edges) == 0:
            return x.new_zeros(x.shape[0])
        e = torch.as_tensor(self.edges, device=x.device)
        length = (x[:, e[:, 1]] - x[:, e[:, 0]]).norm(dim=-1)
        rest = torch.as_tensor(self.rest_length, dtype=x.dtype, device=x.device)
        return (length / rest - 1.0).abs().amax(dim=-1)

    def _depth(self, x: Tensor, bodies: list[Bodies]) -> Tensor:
        """(B,) deepest penetration [m] (>= 0) of the cloth rows of x into the bodies."""
        rows = self.contacts.rows.to(x.device)
        if len(rows) == 0 or not bodies:
            return x.new_zeros(x.shape[0])
        sd = torch.cat([g.depth(x[:, rows])[0] for g in bodies], dim=-1)  # (B, n, K)
        return (-sd.amin(dim=-1)).clamp_min(0.0).amax(dim=-1)

    @torch.no_grad()
    def project(self, x_prev: Tensor, x: Tensor, v: Tensor, dt: float, bodies: list[Bodies],
                pinned: Tensor | None = None) -> tuple[Tensor, Tensor, ProjectionReport]:
        """Projected (x, v) (B, N, 3) of a predicted step x, v from x_prev, and a report. bodies: this step's
        collision bodies (`ContactProjection.boxes` / `rigid`); pinned (B, N) bool: vertices that keep x (e.g.
        held between closed pads)."""
        colours, lo, hi, rest = self._tensors(x)
        inv_mass = torch.ones(x.shape[:2], dtype=x.dtype, device=x.device)
        if pinned is not None:
            inv_mass = inv_mass * (~pinned).to(x.dtype)
        strain_before, depth_before = self.strain(x), self._depth(x, bodies)
        out = x.clone()
        edge_shift = torch.zeros_like(x)
        pushed = torch.zeros(x.shape[:2], dtype=torch.bool, device=x.device)
        normal = torch.zeros_like(x)
        pairs = self.self_contact.pairs(x) if self.self_contact is not None else []
        done = 0
        for done in range(1, self.iterations + 1):
            edge_pass(out, inv_mass, colours, lo, hi, edge_shift)
            cloth = self.contacts.rows.to(x.device)
            if len(cloth) and bodies:
                moved = self.contacts.push_out(out[:, cloth], bodies)
                delta = moved - out[:, cloth]
                hit = delta.norm(dim=-1) > 0
                if pinned is not None:  # a pinned vertex stays where its pads hold it
                    hit &= ~pinned[:, cloth]
                    delta = torch.where(hit[..., None], delta, torch.zeros_like(delta))
                out[:, cloth] += delta
                pushed[:, cloth] |= hit
                normal[:, cloth] = torch.where(hit[..., None], delta / delta.norm(dim=-1, keepdim=True).clamp_min(1e-12),
                                               normal[:, cloth])
            short = self.self_contact.separate(x_prev, out, pairs, inv_mass)[1] if pairs else out.new_zeros(1)
            if bool((self._violation(out, lo, hi) <= self.tolerance_m).all()
                    and (self._depth(out, bodies) <= self.tolerance_m).all() and (short <= self.tolerance_m).all()):
                break
        for _ in range(self.final_edge_passes):  # edges first where the loop left them violated (module doc)
            if bool((self._violation(out, lo, hi) <= self.tolerance_m).all()):
                break
            edge_pass(out, inv_mass, colours, lo, hi, edge_shift)
        v_out = v + edge_shift / dt
        inward = (v_out * normal).sum(-1, keepdim=True).clamp_max(0.0)  # velocity into the surface of a pushed vertex
        v_out = torch.where(pushed[..., None], v_out - inward * normal, v_out)
        violation, depth = self._violation(out, lo, hi), self._depth(out, bodies)
        report = ProjectionReport(strain_before.cpu().numpy(), self.strain(out).cpu().numpy(),
                                  depth_before.cpu().numpy(), depth.cpu().numpy(),
                                  ((violation <= self.tolerance_m) & (depth <= self.tolerance_m)).cpu().numpy(), done)
        return out, v_out, report

    def _violation(self, x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        """(B,) largest distance [m] of an edge length outside its [lo, hi]."""
        if len(self.edges) == 0:
            return x.new_zeros(x.shape[0])
        e = torch.as_tensor(self.edges, device=x.device)
        length = (x[:, e[:, 1]] - x[:, e[:, 0]]).norm(dim=-1)
        return torch.maximum(lo - length, length - hi).clamp_min(0.0).amax(dim=-1)


class JointStepProjection:
    """`ConstraintProjection` as a predictor's per-step projection (the `ContactProjection.project` signature),
    keeping the largest strain and penetration it saw before and after, and the steps that did not converge."""

    def __init__(self, scene, edge_ratio: tuple[float, float], iterations: int,  # noqa: ANN001
                 carry: PadCarry | None = None, untangle: SelfIntersectionGuard | CrossingFreeStep | None = None,
                 self_contact: SelfContactSeparation | None = None, final_edge_passes: int = 0) -> None:
        """carry: cloth held between closed pads follows them and stays pinned (wc.expand.carry); untangle: self-
        crossings the projected step leaves are rolled back (wc.expand.untangle), or the step is bounded so that none
        can form (wc.expand.crossing_free); self_contact: cloth kept a gap
        from its own triangles in the projection (wc.expand.self_contact); None: none of these; final_edge_passes: as
        ConstraintProjection's."""
        self.constraints = ConstraintProjection(scene, edge_ratio, iterations, self_contact=self_contact,
                                                final_edge_passes=final_edge_passes)
        self.scene, self.carry, self.untangle = scene, carry, untangle
        self.stats = {"steps": 0, "not_converged": 0, "max_strain_before": 0.0, "max_strain_after": 0.0,
                      "max_depth_before_m": 0.0, "max_depth_after_m": 0.0, "carried_vertex_steps": 0}

    def boxes(self, link_poses: np.ndarray, like: Tensor) -> Bodies:
        return self.constraints.contacts.boxes(link_poses, like)

    def project(self, x_prev: Tensor, x: Tensor, v: Tensor, dt: float, boxes: Bodies, frame: int,
                link_poses: np.ndarray, prev_link_poses: np.ndarray | None = None) -> tuple[Tensor, Tensor]:
        """As `ContactProjection.project`; prev_link_poses (B, L, 7), the poses at x_prev, for the pad carry."""
        pinned = None
        if self.carry is not None and prev_link_poses is not None:
            x, v, pinned = self.carry.apply(x_prev, x, v, dt, prev_link_poses, link_poses)
            self.stats["carried_vertex_steps"] += int(pinned.sum())
        bodies = [Bodies(boxes.pos[:, frame], boxes.rot[:, frame], boxes.normals, boxes.offsets),
                  *self.constraints.contacts.rigid(x, link_poses)]
        x_out, v_out, r = self.constraints.project(x_prev, x, v, dt, bodies, pinned)
        if self.untangle is not None:
            x_out, v_out = self.untangle.apply(x_prev, x_out, v_out, dt)
        finite = np.isfinite(r.strain_before)
        s = self.stats
        s["steps"] += 1
        s["not_converged"] += int((~r.converged & finite).any())
        for key, values in (("max_strain_before", r.strain_before), ("max_strain_after", r.strain_after),
                            ("max_depth_before_m", r.depth_before), ("max_depth_after_m", r.depth_after)):
            if finite.any():
                s[key] = max(s[key], float(values[finite].max()))
        return x_out, v_out
