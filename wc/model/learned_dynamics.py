"""A learned predictor as `wc.dynamics.Dynamics`: the call the Newton simulator answers (frame-0 object states and
14-D commanded actions in, (x, v) per frame out), for WorldContact, a baseline or a reference alike.

The predictors (wc.eval.predictors.Predictor) step tensors under prescribed body poses; `PrescribedInputs`
(wc.model.prescribed_inputs) turns the actions into those poses: the scene's forward kinematics (expand) or an
episode's recorded poses (evaluate, stress). A batch goes on past an episode that diverges (`finite_rollout`).
A predictor that reads past frames (`history` > 1) is given the frames recorded before the rollout's frame 0 when the
rollout starts from the recorded state there (`RecordedPast`), and the frames it predicted when it is restarted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from wc.dynamics import ObjectState, SteppedEpisode, as_command, finite_state, stepped
from wc.model.layout import SceneLayout
from wc.model.past_frames import PastFrames
from wc.model.prescribed_inputs import PrescribedInputs

if TYPE_CHECKING:
    from wc.model.predictor import Predictor


@dataclass(frozen=True)
class RecordedPast:
    """The K recorded frames before frame 0 of an episode's recorded inputs, and the recorded state at frame 0 (a
    rollout from that state is given them)."""

    x: np.ndarray  # (K, N, 3) m
    v: np.ndarray  # (K, N, 3) m/s
    poses: np.ndarray  # (K, P, 7) the layout's bodies
    start: ObjectState  # the recorded state at frame 0

    def frames_before(self, x0: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """x, v (B, K, N, 3) and poses (B, K, P, 7) when every state of x0, v0 (B, N, 3) is the recorded one, else
        None (the recording says nothing of what led to another state)."""
        same = (x0 == self.start.x).all() and (v0 == self.start.v).all()
        if not same or not len(self.x):
            return None
        return tuple(np.broadcast_to(a, (len(x0), *a.shape)) for a in (self.x, self.v, self.poses))


def finite_rollout(predictor: Predictor, layout: SceneLayout, x0: np.ndarray, v0: np.ndarray, poses: np.ndarray,
                   dt: float, device: torch.device, past: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """x, v (B, T, N, 3) for frames 0..T-1 from x0, v0 (B, N, 3) under poses (B, T, P, 7).

    A predictor may stop the whole batch at the first step where one episode turns non-finite (WorldContact
    does); the episodes still finite there are restarted from that frame, so one diverged episode does not
    cut the others short. A diverged episode stays NaN from the frame it diverged. A predictor that reads
    `history` - 1 past frames is given them (`past` (B, K, ...): x, v, poses before frame 0, then the frames
    predicted before a restart), as wc.model.past_frames.PastFrames."""
    B, T = poses.shape[:2]
    xs = np.full((B, T, *x0.shape[1:]), np.nan, np.float32)
    vs = xs.copy()
    xs[:, 0], vs[:, 0] = x0, v0
    reads = getattr(predictor, "history", 1) - 1
    if past is None:
        past = (xs[:, :0], vs[:, :0], poses[:, :0])
    alive, start = np.arange(B), 0

    def tensor(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(device)

    while len(alive) and start < T - 1:
        extra = {}
        if reads > 0 and len(past[0][0]) + start > 0:
            before = [np.concatenate([p[alive], a[alive, :start]], 1)[:, -reads:] for p, a in zip(past, (xs, vs, poses))]
            extra["past"] = PastFrames(*(tensor(a) for a in before))
        px, pv = predictor.rollout(layout, tensor(xs[alive, start]), tensor(vs[alive, start]),
                                   tensor(poses[alive, start:]), dt, **extra)
        px, pv = (torch.as_tensor(a).detach().float().cpu().numpy() for a in (px, pv))
        xs[alive, start + 1:], vs[alive, start + 1:] = px, pv
        finite = np.isfinite(px).all(axis=(2, 3)) & np.isfinite(pv).all(axis=(2, 3))  # (b, steps)
        if finite.all():
            break
        k = int(np.flatnonzero(~finite.all(axis=0))[0])  # the first step some episode diverged
        alive, start = alive[finite[:, k]], start + 1 + k
    return xs, vs


class LearnedDynamics:
    """`Dynamics` of a predictor over one layout, under prescribed inputs of the layout's bodies.

    `step` gives a predictor the state and the poses of the frame and the next: a predictor that reads more past
    frames (a `history` attribute > 1, as the particle baselines have) is replayed from the state its episode
    (re)started from, so that stepping gives `rollout`'s frames; each step then costs a rollout of the frames so far.
    """

    def __init__(self, predictor: Predictor, layout: SceneLayout, inputs: PrescribedInputs, dt: float,
                 device: torch.device, past: RecordedPast | None = None) -> None:
        if tuple(layout.bodies) != tuple(inputs.bodies):
            raise ValueError(f"layout bodies {layout.bodies} are not the prescribed inputs' bodies {inputs.bodies}")
        if past is not None and past.poses.shape[1:] != (len(layout.bodies), 7):
            raise ValueError(f"recorded past poses {past.poses.shape} are not of the layout's {len(layout.bodies)} "
                             "bodies")
        self.predictor, self.layout, self.inputs, self.dt, self.device = predictor, layout, inputs, dt, device
        self.past = past
        self._episode: SteppedEpisode | None = None

    def rollout_arrays(self, x0: np.ndarray, v0: np.ndarray, actions: np.ndarray, first: int = 0
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, v (B, T, N, 3) (frame 0 = x0, v0; NaN from where an episode diverged) and the body poses (B, T, P, 7)
        of actions (B, T, 14) at frames first..first+T-1; from frame 0's recorded state a model of past frames is
        given the recorded past."""
        actions = np.asarray(actions, np.float32)
        if actions.ndim != 3 or actions.shape[-1] != 14 or actions.shape[0] != len(x0):
            raise ValueError(f"actions must be (B, T, 14) for {len(x0)} states, got {actions.shape}")
        poses = self.inputs.poses(actions, first)
        past = self.past.frames_before(x0, v0) if self.past is not None and first == 0 else None
        x, v = finite_rollout(self.predictor, self.layout, x0, v0, poses, self.dt, self.device, past)
        return x, v, poses

    def rollout_batch(self, initial: list[ObjectState], actions: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """As NewtonSimulator.rollout_batch: episodes of equal length, [(x, v) of (T, N, 3)], not checked finite."""
        lengths = {len(a) for a in actions}
        if len(lengths) != 1 or len(initial) != len(actions):
            raise ValueError(f"need one action sequence per state, all of one length; got {len(initial)} states "
                             f"and lengths {sorted(lengths)}")
        x0 = np.stack([s.x for s in initial]).astype(np.float32)
        v0 = np.stack([s.v for s in initial]).astype(np.float32)
        x, v, _ = self.rollout_arrays(x0, v0, np.stack(actions))
        return [(x[b], v[b]) for b in range(len(initial))]

    def rollout(self, initial: ObjectState, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One episode: (x, v) each (T, N, 3), frame 0 = `initial`."""
        return self.rollout_batch([initial], [actions])[0]

    def start(self, initial: ObjectState, action: np.ndarray) -> None:
        """Frame 0 of a stepped episode: the object state and the robot's command (14,)."""
        self._episode = SteppedEpisode(initial, [as_command(action)])

    def step(self, state: ObjectState, action: np.ndarray) -> ObjectState:
        """The object state one frame after `state` under the poses of the current command and `action` (14,)."""
        nxt = as_command(action)
        episode = stepped(self._episode, state)
        self._episode = None  # until the step is known finite: after a FloatingPointError, start again
        actions = [*episode.actions, nxt]
        replay = getattr(self.predictor, "history", 1) > 1  # a model of past frames: replay from where they start
        origin, first = (episode.origin, episode.first) if replay else (state, episode.frame)
        window = np.stack(actions if replay else actions[-2:])[None]
        x, v, _ = self.rollout_arrays(origin.x[None], origin.v[None], window, first)
        out = finite_state(x[0, -1], v[0, -1], episode.frame + 1)
        episode.actions.append(nxt)
        self._episode, episode.last = episode, out
        return out
