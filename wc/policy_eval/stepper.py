"""One simulated frame at a time for the closed loop: the next action is chosen from the state in between.

A thin adapter over the `wc.dynamics.Dynamics` step of NewtonSimulator (`start`, then `step` from the state it last
gave, so the solver's history goes on): the frames it produces are those of `rollout_batch`, which
tests/test_policy_eval.py checks. A state that turns non-finite comes back as NaN for the environment to judge.
"""

from __future__ import annotations

import numpy as np

from wc.dynamics import ObjectState
from wc.sim.newton_sim import NewtonSimulator


class FrameStepper:
    """Drives world 0 of a one-world simulator frame by frame under 14-D actions."""

    def __init__(self, sim: NewtonSimulator) -> None:
        if sim.worlds != 1:
            raise ValueError(f"FrameStepper needs a one-world simulator, got {sim.worlds} worlds")
        self.sim = sim
        self.state: ObjectState | None = None  # the current frame's object state

    def start(self, state: ObjectState, action: np.ndarray) -> None:
        """Frame 0: object state and robot command (14,); forgets the solver's history."""
        self.sim.start(state, action)
        self.state = state

    def advance(self, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Move the robot from the current command to `action` (14,) over one frame; returns the object state after
        it, x and v (the frame-mean velocity) each (N, 3) float32, NaN once it turned non-finite."""
        if self.state is None:
            raise RuntimeError("FrameStepper.advance before start")
        try:
            self.state = self.sim.step(self.state, action)
        except FloatingPointError:
            self.state = None  # the episode is over: start again
            nan = np.full((self.sim.scene.num_vertices, 3), np.nan, np.float32)
            return nan, nan.copy()
        return self.state.x, self.state.v
