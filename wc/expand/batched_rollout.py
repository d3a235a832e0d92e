"""Batched world-model rollouts of planned episodes: prescribed poses from the commanded actions, then the
predictor steps every episode of the batch together from its frame-0 state."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from wc.agent.runner import pad_to_length
from wc.eval.predictors import Predictor
from wc.expand.plan import PlannedEpisode
from wc.model.layout import SceneLayout
from wc.scene.scene import Scene


@dataclass(frozen=True)
class Rollout:
    """One generated episode in the store's arrays; x, v are NaN from the frame the rollout diverged."""

    x: np.ndarray  # (T, N, 3) m, frame 0 = the planned state
    v: np.ndarray  # (T, N, 3) m/s
    action: np.ndarray  # (T, 14)
    link_poses: np.ndarray  # (T, L, 7) in scene.link_names order
    env_poses: np.ndarray  # (T, E, 7)


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


def rollout_batch(predictor: Predictor, layout: SceneLayout, scene: Scene, planned: list[PlannedEpisode],
                  dt: float, device: torch.device) -> list[Rollout]:
    """Roll out planned episodes together; shorter action sequences hold their last action (as the simulator
    agent pads a batch) until the longest ends."""
    if layout.bodies != (*scene.link_names, *scene.env_names):
        raise ValueError(f"layout bodies {layout.bodies} are not the scene's links then environment "
                         f"{(*scene.link_names, *scene.env_names)}")
    length = max(len(p.actions) for p in planned)
    actions = np.stack([pad_to_length(p.actions, length) for p in planned]).astype(np.float32)  # (B, T, 14)
    links = scene.link_poses(actions)  # (B, T, L, 7)
    env = np.broadcast_to(scene.env_poses(), (*links.shape[:2], *scene.env_poses().shape))
    poses = np.concatenate([links, env], axis=2)
    x0 = np.stack([p.x0 for p in planned]).astype(np.float32)
    x, v = finite_rollout(predictor, layout, x0, np.zeros_like(x0), poses, dt, device)
    return [Rollout(x[b], v[b], actions[b], links[b], np.ascontiguousarray(env[b])) for b in range(len(planned))]
