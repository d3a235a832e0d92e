"""One interface for everything that advances the object state S_t under prescribed inputs B_t.

`Dynamics` is what the Newton source simulator (wc.sim.newton_sim.NewtonSimulator) and every learned predictor -
WorldContact, the baselines, the references - answer alike (the learned ones through
wc.model.learned_dynamics.LearnedDynamics): frame-0 object states and 14-D commanded actions in, (x, v) per frame out.
expand, evaluate, stress and the benchmarks roll every method out through it; the policy environment steps Newton.

Whole episodes: `rollout` / `rollout_batch`. One frame at a time (a closed loop picks the next action from the
state): `start` sets frame 0 and the robot's command, then each `step` moves the robot to the next command over one
frame and returns the object state after it. A model with history (Newton's solver; a learned model that reads past
frames) continues it while `step` is given the state the last `start` / `step` left, and starts afresh from any other
state (at the current command and frame). Stepping through an episode's actions from `start` gives `rollout`'s frames
(to float rounding).
"""

from __future__ import annotations

from dataclasses import dataclass, field
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

    def start(self, initial: ObjectState, action: np.ndarray) -> None:
        """Frame 0 of a stepped episode: the object state and the robot's command (14,); forgets any history."""
        ...

    def step(self, state: ObjectState, action: np.ndarray) -> ObjectState:
        """The object state one frame after `state` as the robot moves from the current command to `action` (14,);
        FloatingPointError when it is non-finite (then `start` again), RuntimeError before `start`."""
        ...


def as_command(action: np.ndarray) -> np.ndarray:
    """One 14-D command as float32 (14,); ValueError naming any other shape."""
    a = np.asarray(action, np.float32)
    if a.shape not in ((14,), (1, 14)):
        raise ValueError(f"a step's action must be (14,), got {a.shape}")
    return a.reshape(14)


def finite_state(x: np.ndarray, v: np.ndarray, frame: int) -> ObjectState:
    """x, v (N, 3) as an ObjectState; FloatingPointError naming the frame when either is non-finite."""
    if not (np.isfinite(x).all() and np.isfinite(v).all()):
        raise FloatingPointError(f"the object state turned non-finite at frame {frame}")
    return ObjectState(x, v)


@dataclass
class SteppedEpisode:
    """Where a stepped episode stands: the state it (re)started from at frame `first`, the commands since (the first
    is the command at that state) and the last state given out."""

    origin: ObjectState
    actions: list[np.ndarray]
    first: int = 0
    last: ObjectState = field(init=False)

    def __post_init__(self) -> None:
        self.last = self.origin

    @property
    def frame(self) -> int:
        """The frame of `last`."""
        return self.first + len(self.actions) - 1

    @property
    def action(self) -> np.ndarray:
        """The robot's current command (14,)."""
        return self.actions[-1]

    def continues(self, state: ObjectState) -> bool:
        """Whether `state` is the last state given out (its history may go on)."""
        return state is self.last or (np.array_equal(state.x, self.last.x) and np.array_equal(state.v, self.last.v))

    def restarted(self, state: ObjectState) -> SteppedEpisode:
        """A new history from `state` at the current command and frame."""
        return SteppedEpisode(state, [self.action], self.frame)


def stepped(episode: SteppedEpisode | None, state: ObjectState) -> SteppedEpisode:
    """The episode a `step` from `state` continues: `episode`, or one restarted from `state`; RuntimeError before
    `start`."""
    if episode is None:
        raise RuntimeError("step before start: call start(initial, action) first")
    return episode if episode.continues(state) else episode.restarted(state)
