"""Batched world-model rollouts of planned episodes: the predictor, as `Dynamics` (wc.model.learned_dynamics), steps
every episode of the batch together from its frame-0 state under its commanded actions (the robot's poses from the
scene's forward kinematics, KinematicInputs)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from wc.agent.runner import pad_to_length
from wc.model.predictor import Predictor
from wc.expand.plan import PlannedEpisode
from wc.model.layout import SceneLayout
from wc.model.learned_dynamics import LearnedDynamics
from wc.model.prescribed_inputs import KinematicInputs
from wc.scene.scene import Scene


@dataclass(frozen=True)
class Rollout:
    """One generated episode in the store's arrays; x, v are NaN from the frame the rollout diverged."""

    x: np.ndarray  # (T, N, 3) m, frame 0 = the planned state
    v: np.ndarray  # (T, N, 3) m/s
    action: np.ndarray  # (T, 14)
    link_poses: np.ndarray  # (T, L, 7) in scene.link_names order
    env_poses: np.ndarray  # (T, E, 7)


def rollout_batch(predictor: Predictor, layout: SceneLayout, scene: Scene, planned: list[PlannedEpisode],
                  dt: float, device: torch.device) -> list[Rollout]:
    """Roll out planned episodes together (wc.model.learned_dynamics: the predictor as `Dynamics`); shorter action
    sequences hold their last action (as the simulator agent pads a batch) until the longest ends."""
    dynamics = LearnedDynamics(predictor, layout, KinematicInputs(scene), dt, device)
    length = max(len(p.actions) for p in planned)
    actions = np.stack([pad_to_length(p.actions, length) for p in planned]).astype(np.float32)  # (B, T, 14)
    x0 = np.stack([p.x0 for p in planned]).astype(np.float32)
    x, v, poses = dynamics.rollout_arrays(x0, np.zeros_like(x0), actions)
    links, env = np.split(poses, [len(scene.link_names)], axis=2)
    return [Rollout(x[b], v[b], actions[b], np.ascontiguousarray(links[b]), np.ascontiguousarray(env[b]))
            for b in range(len(planned))]
