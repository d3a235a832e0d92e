"""Rigid pose and twist of a rigid object from its vertex positions and velocities."""

from __future__ import annotations

import numpy as np

from wc.rotations import quat_from_matrix


def rigid_pose_from_vertices(rest: np.ndarray, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best-fit pose (7,) [pos, quat xyzw] mapping rest-frame vertices onto x (Kabsch), and the
    twist (6,) [linear of the rest origin, angular] that best explains velocities v."""
    rc, xc = rest.mean(0), x.mean(0)
    u, _, vt = np.linalg.svd((rest - rc).T @ (x - xc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    pos = xc - rot @ rc
    r = x - pos  # lever arms from the body origin
    # v_i = lin + w x r_i  ->  least squares over [lin, w]
    skew = np.zeros((len(r), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = r[:, 2], -r[:, 1], r[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = -r[:, 2], r[:, 1], -r[:, 0]
    a = np.concatenate([np.tile(np.eye(3), (len(r), 1, 1)), skew], axis=2).reshape(-1, 6)
    twist = np.linalg.lstsq(a, v.reshape(-1), rcond=None)[0]
    return np.concatenate([pos, quat_from_matrix(rot)]).astype(np.float32), twist.astype(np.float32)
