"""The particle baselines' map-back floor: their vertex error with perfect particle predictions.

A particle baseline (wc.baselines) predicts K object particles and rebuilds every vertex from them
(wc.baselines.sampling.ParticleMap: each vertex follows its nearest particles' displacement since the first frame).
Rebuilding the recorded frames from their own recorded particles gives the error that is left when every particle is
right: the floor its particle count sets on that baseline's vertex position MSE, measured here on the same held-out
frames as its rollouts (zero when every vertex is a particle).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from wc.baselines.base import ParticleDynamics
from wc.baselines.sampling import ParticleMap
from wc.eval.cases import Case
from wc.eval.methods import LearnedMethod, Method
from wc.eval.metrics import ErrorTally


def particle_map(method: Method, case: Case) -> ParticleMap | None:
    """The particle map `method` uses on the case's layout; None for a method that predicts every vertex."""
    if isinstance(method, LearnedMethod) and isinstance(method.predictor, ParticleDynamics):
        return method.predictor.scene(case.layout).particles
    return None


def mapped_back(pmap: ParticleMap, x: np.ndarray) -> np.ndarray:
    """Frames 1..T-1 of `x` (T, N, 3) rebuilt from their own particles and frame 0, as (T-1, N, 3) float64."""
    x = np.asarray(x, np.float64)
    if x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] < 2:
        raise ValueError(f"map back needs frames (T >= 2, N, 3), got {x.shape}")
    if x.shape[1] != pmap.neighbors.shape[0]:
        raise ValueError(f"the particle map has {pmap.neighbors.shape[0]} vertices, the frames {x.shape[1]}")
    xt = torch.from_numpy(x)
    cpu = ParticleMap(pmap.vertices.cpu(), pmap.object_id.cpu(), pmap.neighbors.cpu(), pmap.weights.cpu().double())
    p = xt[:, cpu.vertices]
    return cpu.to_vertices(xt[None, 0], p[None, 0], p[None, 1:])[0].numpy()


@dataclass
class MapBackTally:
    """Map-back errors of each particle method over the scored held-out rollouts (the frames each is scored on)."""

    horizon: int  # the longest scored rollout, in steps
    errors: dict[str, ErrorTally] = field(default_factory=dict)
    sizes: dict[str, set[tuple[int, int]]] = field(default_factory=dict)  # (particles, vertices) per layout seen

    def add(self, name: str, method: Method, case: Case) -> None:
        """The case's recorded frames rebuilt through `method`'s particles (no-op for a method without them)."""
        pmap = particle_map(method, case)
        if pmap is None:
            return
        truth = np.asarray(case.x, np.float64)
        rebuilt = mapped_back(pmap, truth)
        zero = np.zeros_like(rebuilt)
        self.errors.setdefault(name, ErrorTally(self.horizon)).add(case.task, rebuilt, zero, truth[1:], zero)
        self.sizes.setdefault(name, set()).add((int(pmap.vertices.shape[0]), int(truth.shape[1])))

    def summary(self) -> dict[str, dict[str, Any]]:
        """{method: {position_mse_m2, per_task: {task: position_mse_m2}, layouts: [{particles, vertices}]}}."""
        out = {}
        for name, tally in self.errors.items():
            s = tally.summary()
            out[name] = {"position_mse_m2": s["position_mse_m2"],
                         "per_task": {t: m["position_mse_m2"] for t, m in s["per_task"].items()},
                         "layouts": [{"particles": k, "vertices": n} for k, n in sorted(self.sizes[name])]}
        return out
