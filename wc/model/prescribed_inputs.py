"""The prescribed inputs B_t a learned predictor steps under, from the commanded actions: body poses (B, T, P, 7) of
a layout's bodies (wc.model.layout.SceneLayout.bodies: robot links and held objects, then environment bodies).

    KinematicInputs  the scene's forward kinematics of the actions, the environment where the scene stands it
                     (expand: generated episodes have no recording)
    RecordedInputs   the poses recorded beside one episode's actions (evaluate, stress: the store's link, held-object
                     and environment poses, whatever layout the episode had); it answers those actions only
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from wc.scene.scene import Scene


class PrescribedInputs(Protocol):
    bodies: tuple[str, ...]

    def poses(self, actions: np.ndarray, first: int = 0) -> np.ndarray:
        """Poses (B, T, P, 7) of `bodies` at frames first..first+T-1 of an episode under actions (B, T, 14)."""
        ...


class KinematicInputs:
    """Link poses from the scene's forward kinematics (held objects ride on their links), then the environment."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.bodies = (*scene.link_names, *scene.env_names)

    def poses(self, actions: np.ndarray, first: int = 0) -> np.ndarray:
        links = self.scene.link_poses(actions)  # (B, T, L, 7); the frame index does not matter
        env = self.scene.env_poses()
        env = np.broadcast_to(env, (*links.shape[:2], *env.shape))
        return np.concatenate([links, env], axis=2)


class RecordedInputs:
    """The poses (T, P, 7) of `bodies` recorded with an episode's actions (T, 14), frame by frame."""

    def __init__(self, actions: np.ndarray, poses: np.ndarray, bodies: tuple[str, ...]) -> None:
        self.actions = np.asarray(actions, np.float32)
        self.recorded = np.asarray(poses, np.float32)
        self.bodies = tuple(bodies)
        if self.actions.ndim != 2 or self.actions.shape[1] != 14 or self.recorded.shape != (
                len(self.actions), len(self.bodies), 7):
            raise ValueError(f"recorded inputs need actions (T, 14) and poses (T, {len(self.bodies)}, 7) of the same "
                             f"T, got {self.actions.shape} and {self.recorded.shape}")

    def poses(self, actions: np.ndarray, first: int = 0) -> np.ndarray:
        """The recorded poses of frames first..first+T-1; ValueError unless actions (B, T, 14) are the recorded ones
        there (a recording says nothing about other actions)."""
        steps = actions.shape[1]
        recorded = self.actions[first:first + steps]
        if first < 0 or len(recorded) != steps or not (np.asarray(actions, np.float32) == recorded).all():
            raise ValueError(f"actions of frames {first}..{first + steps - 1} are not the recorded ones (frames "
                             f"0..{len(self.actions) - 1}): recorded inputs answer only their own episode's actions")
        window = self.recorded[first:first + steps]
        return np.broadcast_to(window, (actions.shape[0], *window.shape))
