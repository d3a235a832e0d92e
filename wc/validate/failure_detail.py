"""What made an episode fail, for the reports: which blow_up criterion fired, which body the cloth went into."""

from __future__ import annotations

import numpy as np

from wc.scene.scene import Scene
from wc.validate.config import ValidateConfig
from wc.validate.predicates import (Episode, box_signed_distance, cloth_rows, convex_depth, convex_planes,
                                    rigid_poses, robot_box_shapes, robot_boxes, speed_and_strain,
                                    table_distance)


def blow_up_detail(scene: Scene, ep: Episode, cfg: ValidateConfig, frame: int) -> dict[str, object]:
    """Which blow_up criterion fired at `frame` ("speed", "strain" or "speed+strain"), with both values there."""
    speed, strain = speed_and_strain(scene, ep)
    fired = [name for name, value, limit in (("speed", speed[frame], cfg.max_speed_m_s),
                                             ("strain", strain[frame], cfg.max_edge_strain)) if value > limit]
    return {"criterion": "+".join(fired), "max_speed_m_s": float(speed[frame]), "max_edge_strain": float(strain[frame])}


def penetration_detail(scene: Scene, ep: Episode, cfg: ValidateConfig, frame: int) -> dict[str, object]:
    """The body a cloth vertex is deepest inside at `frame` ("table", a robot link such as "left_link6", or a rigid
    object) and that depth [m], beside the tolerance."""
    at = Episode(*(a[frame:frame + 1] for a in (ep.x, ep.v, ep.action, ep.link_poses)), ep.frame_dt_s)  # that frame
    x = np.asarray(at.x[:, cloth_rows(scene)], np.float64)  # (1, N, 3)
    depth = {"table": float(-table_distance(scene, x).min())}
    centre, quat, half = robot_boxes(scene, at.link_poses)
    for b, (k, _) in enumerate(robot_box_shapes(scene)):
        inside = float(-box_signed_distance(x, centre[:, b, None], quat[:, b, None], half[b]).min())
        depth[scene.link_names[k]] = max(depth.get(scene.link_names[k], -np.inf), inside)
    for name, mesh, pos, rot in rigid_poses(scene, at):  # fitted on that frame only
        planes = convex_planes(mesh.vertices, mesh.faces, name)
        depth[name] = float(convex_depth(x, pos, rot, planes)[0])
    body = max(depth, key=lambda name: depth[name])
    return {"body": body, "depth_m": depth[body], "tolerance_m": cfg.penetration_tol_m}


def failure_detail(scene: Scene, ep: Episode, cfg: ValidateConfig, reason: str, frame: int) -> dict[str, object]:
    """A blow_up's criterion or a penetration's body at the failing frame; {} for the other reasons."""
    if reason == "blow_up":
        return blow_up_detail(scene, ep, cfg, frame)
    if reason == "penetration":
        return penetration_detail(scene, ep, cfg, frame)
    return {}
