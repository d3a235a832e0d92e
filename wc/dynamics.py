"""One interface for everything that advances the object state S_t under prescribed inputs B_t.

`Dynamics` is what the Newton source simulator (wc.sim.newton_sim.NewtonSimulator) and every learned predictor -
WorldContact, the baselines, the references - answer alike: frame-0 object states and 14-D commanded actions in,
(x, v) per frame out (the learned ones through wc.model.learned_dynamics.LearnedDynamics, which the expand stage
rolls out with).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass
class ObjectState:
    """S_t without the static parts: vertex positions and velocities of all predicted objects."""

    x: np.ndarray  # (N, 3) float32 [m]
    v: np.ndarray  # (N, 3) float32 [m/s]

    def __post_init__(self) -> None:
        if self.x.shape != self.v.shape or self.x.ndim != 2 or self.x.shape[1] != 3:
            raise ValueError(f"x and v must both be (N, 3), got {self.x.shape} and {self.v.shape}")
        if not (np.isfinite(self.x).all() and np.isfinite(self.v).all()):
            raise ValueError("object state has non-finite positions or velocities")


@runtime_checkable
class Dynamics(Protocol):
    """Advances S_t by frames of the recorded frame dt under commanded actions a_t (14-D)."""

    def rollout(self, initial: ObjectState, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x, v), each (T, N, 3), from frame-0 state `initial` under actions (T, 14)."""
        ...

    def rollout_batch(self, initial: list[ObjectState], actions: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Several episodes of equal length at once."""
        ...
