"""The camera rig of the rendered views: scene.cameras at the render resolution, posed per frame
(top fixed in the world; wrist riding on its link, e.g. right_link6)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from wc.scene.cameras import camera_pose
from wc.scene.config import CameraConfig


def render_cameras(cameras: Mapping[str, CameraConfig], names: Sequence[str], width: int,
                   height: int) -> dict[str, CameraConfig]:
    """The named cameras of scene.cameras at width x height [px] (same vertical field of view)."""
    missing = [n for n in names if n not in cameras]
    if missing:
        raise ValueError(f"render.cameras names {missing}, not in scene.cameras {sorted(cameras)}")
    return {n: dataclasses.replace(cameras[n], width=int(width), height=int(height)) for n in names}


def check_camera_links(cameras: Mapping[str, CameraConfig], link_names: Sequence[str], where: str) -> None:
    """Raise a clear error if a camera rides on a link the episode has no pose for."""
    for name, cfg in cameras.items():
        if cfg.link is not None and cfg.link not in link_names:
            raise ValueError(f"{where}: camera {name!r} rides on link {cfg.link!r}, which the episode has no "
                             f"link_poses column for (links: {list(link_names)})")


def camera_transforms(cfg: CameraConfig, link_names: Sequence[str], link_poses: np.ndarray) -> np.ndarray:
    """(T, 7) world camera poses (pos m, quat xyzw) for link poses (T, L, 7); the camera frame is OpenGL's
    (x right, y up, looking along -z), as Newton's SensorCamera expects."""
    names = tuple(link_names)
    out = np.empty((len(link_poses), 7), np.float64)
    for k, poses in enumerate(link_poses):
        eye, rot = camera_pose(cfg, names, poses)
        out[k, :3], out[k, 3:] = eye, Rotation.from_matrix(rot).as_quat()
    return out.astype(np.float32)
