"""A learned predictor as `wc.dynamics.Dynamics`: the call the Newton simulator answers (frame-0 object states and
14-D commanded actions in, (x, v) per frame out), for WorldContact, a baseline or a reference alike.

The predictors (wc.eval.predictors.Predictor) step tensors under prescribed body poses; this turns the actions into
those poses (the scene's forward kinematics for the robot links, the environment bodies where they stand) and keeps
a batch going past an episode that diverges (`finite_rollout`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from wc.dynamics import ObjectState
from wc.model.layout import SceneLayout
from wc.scene.scene import Scene

if TYPE_CHECKING:
    from wc.eval.predictors import Predictor


def finite_rollout(predictor: Predictor, layout: SceneLayout, x0: np.ndarray, v0: np.ndarray, poses: np.ndarray,
                   dt: float, device: torch.device) -> tuple[np.ndarray, np.ndarray]:
    """x, v (B, T, N, 3) for frames 0..T-1 from x0, v0 (B, N, 3) under poses (B, T, P, 7).

    A predictor may stop the whole batch at the first step where one episode turns non-finite (WorldContact
    does); the episodes still finite there are restarted from that frame, so one diverged episode does not
    cut the others short. A diverged episode stays NaN from the frame it diverged."""
    B, T = poses.shape[:2]
    xs = np.full((B, T, *x0.shape[1:]), np.nan, np.float32)
    vs = xs.copy()
    xs[:, 0], vs[:, 0] = x0, v0
    alive, start = np.arange(B), 0
    while len(alive) and start < T - 1:
        def tensor(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(device)

        px, pv = predictor.rollout(layout, tensor(xs[alive, start]), tensor(vs[alive, start]),
                                   tensor(poses[alive, start:]), dt)
        px, pv = (torch.as_tensor(a).detach().float().cpu().numpy() for a in (px, pv))
        xs[alive, start + 1:], vs[alive, start + 1:] = px, pv
        finite = np.isfinite(px).all(axis=(2, 3)) & np.isfinite(pv).all(axis=(2, 3))  # (b, steps)
        if finite.all():
            break
        k = int(np.flatnonzero(~finite.all(axis=0))[0])  # the first step some episode diverged
        alive, start = alive[finite[:, k]], start + 1 + k
    return xs, vs


class LearnedDynamics:
    """`Dynamics` of a predictor over one scene: layout.bodies must be the scene's links, then its environment."""

    def __init__(self, predictor: Predictor, layout: SceneLayout, scene: Scene, dt: float,
                 device: torch.device) -> None:
        if tuple(layout.bodies) != (*scene.link_names, *scene.env_names):
            raise ValueError(f"layout bodies {layout.bodies} are not the scene's links then environment "
                             f"{(*scene.link_names, *scene.env_names)}")
        self.predictor, self.layout, self.scene, self.dt, self.device = predictor, layout, scene, dt, device

    def body_poses(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Link poses (B, T, L, 7) and environment poses (B, T, E, 7) under actions (B, T, 14)."""
        links, env = self.scene.link_poses(actions), self.scene.env_poses()
        env = np.broadcast_to(env, (*links.shape[:2], *env.shape))
        return links, np.ascontiguousarray(env)

    def rollout_arrays(self, x0: np.ndarray, v0: np.ndarray, actions: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """x, v (B, T, N, 3) (frame 0 = x0, v0; NaN from where an episode diverged) and the link and environment
        poses of actions (B, T, 14)."""
        actions = np.asarray(actions, np.float32)
        if actions.ndim != 3 or actions.shape[-1] != 14 or actions.shape[0] != len(x0):
            raise ValueError(f"actions must be (B, T, 14) for {len(x0)} states, got {actions.shape}")
        links, env = self.body_poses(actions)
        x, v = finite_rollout(self.predictor, self.layout, x0, v0, np.concatenate([links, env], axis=2), self.dt,
                              self.device)
        return x, v, links, env

    def rollout_batch(self, initial: list[ObjectState], actions: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """As NewtonSimulator.rollout_batch: episodes of equal length, [(x, v) of (T, N, 3)], not checked finite."""
        lengths = {len(a) for a in actions}
        if len(lengths) != 1 or len(initial) != len(actions):
            raise ValueError(f"need one action sequence per state, all of one length; got {len(initial)} states "
                             f"and lengths {sorted(lengths)}")
        x0 = np.stack([s.x for s in initial]).astype(np.float32)
        v0 = np.stack([s.v for s in initial]).astype(np.float32)
        x, v, _, _ = self.rollout_arrays(x0, v0, np.stack(actions))
        return [(x[b], v[b]) for b in range(len(initial))]

    def rollout(self, initial: ObjectState, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One episode: (x, v) each (T, N, 3), frame 0 = `initial`."""
        return self.rollout_batch([initial], [actions])[0]
