"""Prescribed robot motion per solver substep: interpolated actions -> link poses and twists."""

from __future__ import annotations

import numpy as np

from wc.rotations import quat_conjugate, quat_multiply, quat_rotate


def interpolate_actions(action_now: np.ndarray, action_next: np.ndarray, substeps: int) -> np.ndarray:
    """Commanded actions at the end of each substep between two frames: (substeps, A)."""
    alpha = (np.arange(1, substeps + 1, dtype=np.float64) / substeps)[:, None]
    return ((1.0 - alpha) * action_now[None] + alpha * action_next[None]).astype(np.float32)


def pose_twists(poses_prev: np.ndarray, poses: np.ndarray, dt: float) -> np.ndarray:
    """Body twists [linear m/s, angular rad/s] (world frame) moving poses_prev -> poses in dt.

    poses: (..., 7) pos + quat xyzw. Angular velocity from the relative rotation's axis-angle.
    """
    lin = (poses[..., :3] - poses_prev[..., :3]) / dt
    dq = quat_multiply(poses[..., 3:], quat_conjugate(poses_prev[..., 3:]))
    dq = np.where(dq[..., 3:4] < 0.0, -dq, dq)  # shortest arc
    sin_half = np.linalg.norm(dq[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, dq[..., 3:4])
    axis = dq[..., :3] / np.maximum(sin_half, 1e-12)
    ang = axis * angle / dt
    return np.concatenate([lin, ang], axis=-1).astype(np.float32)


def transform_points(poses: np.ndarray, local: np.ndarray) -> np.ndarray:
    """World positions of body-local points: poses (..., 7), local (M, 3) -> (..., M, 3)."""
    return poses[..., None, :3] + quat_rotate(poses[..., None, 3:], local)
