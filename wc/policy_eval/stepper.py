"""One simulated frame at a time: the closed loop needs what NewtonSimulator.rollout_batch does internally
(write the frame-0 state, advance one frame, read the state back) with the next action chosen in between.

It drives NewtonSimulator's public per-frame API (`set_state`, `advance_frame`, `read_state`, the steps
`rollout_batch` is made of); the frames it produces are those of `rollout_batch` (same solver history, same
substeps), which tests/test_policy_eval.py checks.
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
        self.action: np.ndarray | None = None  # (14,) the robot's current command

    def start(self, state: ObjectState, action: np.ndarray) -> None:
        """Frame 0: object state and robot command (14,); forgets the solver's history."""
        self.action = np.asarray(action, np.float32).reshape(14)
        self.sim.set_state([state], self.action[None])

    def advance(self, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Move the robot from the current command to `action` (14,) over one frame; returns the object
        state after it, x and v each (N, 3) float32, not checked finite (the last substep's velocity)."""
        if self.action is None:
            raise RuntimeError("FrameStepper.advance before start")
        nxt = np.asarray(action, np.float32).reshape(14)
        self.sim.advance_frame(self.action[None], nxt[None])
        self.action = nxt
        x, v = self.sim.read_state()
        return x[0], v[0]
