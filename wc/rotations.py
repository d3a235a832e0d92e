"""Rotations, one module: unit quaternions in xyzw order (the store's and warp's), broadcasting over leading axes.

NumPy for the simulator side (scene, validate, expand), torch where gradients or the GPU need them (forward
kinematics, the model's layout, the baselines): `quat_rotate` / `quat_rotate_torch` and `quat_matrices` /
`quat_matrices_torch` are the same maps.
"""

from __future__ import annotations

import numpy as np
import torch


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of xyzw quaternions."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion) of xyzw quaternions q (..., 4), in q's dtype."""
    return q * np.array([-1.0, -1.0, -1.0, 1.0], q.dtype)


def quat_rotate(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Rotate points p (..., 3) by unit xyzw quaternions q (..., 4)."""
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(u, p)
    return p + w * t + np.cross(u, t)


def quat_matrices(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) (columns: the rotated frame's axes) of xyzw quaternions (..., 4), float64."""
    q = np.asarray(quat, np.float64)
    cols = quat_rotate(q[..., None, :], np.eye(3))  # (..., 3 axes, 3): the rotated basis vectors
    return np.swapaxes(cols, -1, -2)


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit xyzw quaternion of a rotation matrix (3, 3)."""
    w = np.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    x = np.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2.0
    y = np.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2.0
    z = np.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2.0
    x = np.copysign(x, r[2, 1] - r[1, 2])
    y = np.copysign(y, r[0, 2] - r[2, 0])
    z = np.copysign(z, r[1, 0] - r[0, 1])
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def quat_rotate_torch(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v [..., 3] by unit xyzw quaternions q [..., 4] (differentiable)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + w * t + torch.linalg.cross(u, t, dim=-1)


def quat_matrices_torch(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] (columns: the rotated frame's axes) of unit xyzw quaternions [..., 4]."""
    x, y, z, w = q.unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def quat_multiply_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of xyzw quaternions [..., 4] (as `quat_multiply`)."""
    ax, ay, az, aw = a.unbind(-1)
    bx, by, bz, bw = b.unbind(-1)
    return torch.stack([aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw,
                        aw * bw - ax * bx - ay * by - az * bz], dim=-1)
