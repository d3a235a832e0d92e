"""Camera rigs for rendering: a fixed top camera and cameras riding on a robot link (the wrist)."""

from __future__ import annotations

import numpy as np

from wc.scene.config import CameraConfig
from wc.rotations import quat_matrices


def look_at_rotation(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(3, 3) camera-to-frame rotation, OpenGL convention: columns x right, y up, z backwards."""
    back = eye - target
    if np.linalg.norm(back) < 1e-9:
        raise ValueError("camera position and look-at point coincide")
    z = back / np.linalg.norm(back)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("camera up vector is parallel to its viewing direction")
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def intrinsics(cfg: CameraConfig) -> np.ndarray:
    """(3, 3) pinhole intrinsics [px] from the vertical field of view and the resolution."""
    f = 0.5 * cfg.height / np.tan(np.deg2rad(cfg.fov_deg) / 2.0)
    return np.array([[f, 0.0, cfg.width / 2.0], [0.0, f, cfg.height / 2.0], [0.0, 0.0, 1.0]])


def camera_pose(cfg: CameraConfig, link_names: tuple[str, ...], link_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World camera position (..., 3) and rotation (..., 3, 3) given robot link poses (..., L, 7): one frame's
    (L, 7) or many frames' at once."""
    eye, target, up = (np.asarray(v, np.float64) for v in (cfg.position_m, cfg.look_at_m, cfg.up))
    rot = look_at_rotation(eye, target, up)
    frames = np.shape(link_poses)[:-2]
    if cfg.link is None:
        if not frames:
            return eye, rot
        return np.broadcast_to(eye, (*frames, 3)).copy(), np.broadcast_to(rot, (*frames, 3, 3)).copy()
    if cfg.link not in link_names:
        raise ValueError(f"camera link {cfg.link!r} is not a robot body; known: {list(link_names)}")
    pose = np.asarray(link_poses, np.float64)[..., link_names.index(cfg.link), :]
    link_rot = quat_matrices(pose[..., 3:])
    return pose[..., :3] + link_rot @ eye, link_rot @ rot
