"""A predicted step never leaves the cloth crossing itself (an option of the expand stage's projection).

A learnt step can move one layer of cloth through another (a strap squeezed between closing pads, a bag wall
folding onto itself). Newton's self-contact prevents this; the network only learns it approximately. This is the
fail-safe of cloth simulators (Bridson et al. 2002's rollback of colliding regions): after the step is projected,
every cloth mesh is checked for an edge crossing a non-adjacent triangle (the validate stage's own check,
wc.validate.self_intersection); the vertices of each crossing edge and crossed triangle - and, from the second
round on, their mesh neighbours - take a shorter step from the previous, crossing-free state:
x = x_prev + a (x - x_prev), v = a v with a = 1/2, 1/4, ... and 0 from round `rounds` on (the previous state
itself), the rolled-back region growing by a ring each round until no crossing is left.
Positions and velocities stay consistent and no velocity is invented. Nothing is bag-specific: every cloth object.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from wc.validate.predicates import cloth_rows
from wc.validate.self_intersection import crossing_edges, unique_edges


class SelfIntersectionGuard:
    """Rolls back the cloth vertices of a step's self-crossings (module docstring).

    rounds: the round from which the step is rolled back whole (a = 0); device: warp device of the check.
    """

    def __init__(self, scene, rounds: int = 4, device: str = "cpu") -> None:  # noqa: ANN001
        if rounds < 1:
            raise ValueError(f"untangle rounds must be >= 1, got {rounds}")
        self.rounds, self.device = rounds, device
        slices = scene.vertex_slices()
        self.meshes = [(slices[n], np.asarray(m.faces, np.int32), unique_edges(m.faces))
                       for n, m in scene.objects.items() if scene.object_kinds[n] == "cloth"]
        self.cloth_rows = cloth_rows(scene)
        self.stats = {"steps_with_crossings": 0, "rolled_back_vertex_steps": 0, "unresolved_steps": 0}

    def crossing_vertices(self, x: np.ndarray) -> np.ndarray:
        """(N,) bool: cloth vertices of x (N, 3) on a crossing edge or a crossed triangle."""
        involved = np.zeros(len(x), bool)
        for sl, faces, edges in self.meshes:
            hits = crossing_edges(x[sl], faces, edges, self.device)
            crossing = hits >= 0
            if crossing.any():
                rows = np.concatenate([edges[crossing].ravel(), faces[hits[crossing]].ravel()])
                involved[sl.start + rows] = True
        return involved

    def _grow(self, mask: np.ndarray) -> np.ndarray:
        """mask (N,) widened by one ring of mesh neighbours."""
        out = mask.copy()
        for sl, _, edges in self.meshes:
            e = edges + sl.start
            out[e[mask[e[:, 0]], 1]] = True
            out[e[mask[e[:, 1]], 0]] = True
        return out

    @torch.no_grad()
    def apply(self, x_prev: Tensor, x: Tensor, v: Tensor, dt: float | None = None) -> tuple[Tensor, Tensor]:
        """(x, v) (B, N, 3) of a step from x_prev with every self-crossing rolled back (module docstring); dt is
        not needed (velocities scale with the step), taken for the `CrossingFreeStep.apply` signature."""
        if not self.meshes:
            return x, v
        x_out, v_out = x.clone(), v.clone()
        for b in range(x.shape[0]):
            now = x_out[b].detach().float().cpu().numpy()
            if not np.isfinite(now).all():
                continue  # a diverged episode is the blow-up check's to reject
            involved = self.crossing_vertices(now)
            if not involved.any():
                continue
            self.stats["steps_with_crossings"] += 1
            rolled = np.zeros(len(now), bool)
            r = 0
            while involved.any() and not rolled[self.cloth_rows].all():
                r += 1
                rolled |= involved if r == 1 else self._grow(rolled | involved)
                a = 0.5 ** r if r < self.rounds else 0.0
                idx = torch.as_tensor(np.flatnonzero(rolled), device=x.device)
                x_out[b, idx] = x_prev[b, idx] + a * (x[b, idx] - x_prev[b, idx])
                v_out[b, idx] = a * v[b, idx]
                involved = self.crossing_vertices(x_out[b].detach().float().cpu().numpy())
            self.stats["unresolved_steps"] += int(involved.any())  # x_prev crossed: the validate check rejects it
            self.stats["rolled_back_vertex_steps"] += int(rolled.sum())
        return x_out, v_out
