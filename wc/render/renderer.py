"""Raytraced RGB views of stored episodes with Newton's SensorCamera (CPU or CUDA).

One Newton model per geometry layout holds `batch` copies of the scene, one model world per frame;
a batch of frames is one state upload, one BVH refit and one SensorCamera call per camera. The
bodies carry no joints or solver: their poses are written straight into `State.body_q` and the
surface vertices into `State.particle_q`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import wc.warp_settings  # noqa: F401  (first: kernels take warp's settings when defined)
import newton
import numpy as np
import warp as wp
from newton.sensors import SensorCamera

from wc.render.geometry import TABLE_COLOR, EpisodeGeometry
from wc.render.rig import camera_transforms, check_camera_links
from wc.scene.config import CameraConfig

BACKGROUND_RGB = (200, 212, 226)  # light grey-blue wall, unlike any object
LIGHT_DIRECTION = (0.25, 0.45, -0.86)  # key light travel direction: from above, behind the top camera
LIGHT_COLOR = (0.95, 0.95, 0.92)
AMBIENT_SKY = (0.38, 0.38, 0.40)
AMBIENT_GROUND = (0.12, 0.12, 0.13)
PARTICLE_RADIUS_M = 1e-3  # bounds only: particles on triangles are drawn as the surface, not spheres


def _packed_rgba(rgb: tuple[int, int, int]) -> int:
    r, g, b = rgb
    return r | (g << 8) | (b << 16) | (255 << 24)


def _transform(pose: np.ndarray | tuple[float, ...]) -> wp.transform:
    p = [float(v) for v in pose]
    return wp.transform(wp.vec3(*p[:3]), wp.quat(*p[3:]))


def _add_world(builder: newton.ModelBuilder, geometry: EpisodeGeometry) -> None:
    """One copy of the episode's bodies and surfaces in the builder's current world."""
    for body in geometry.bodies:
        index = builder.add_body(xform=wp.transform_identity(), label=body.name)
        for s in body.shapes:
            xform = _transform((*s.local_pos, *s.local_quat_xyzw))
            if s.kind == "box":
                builder.add_shape_box(index, xform=xform, hx=s.size[0], hy=s.size[1], hz=s.size[2], color=body.color)
            else:
                builder.add_shape_capsule(index, xform=xform, radius=s.size[0], half_height=s.size[1],
                                          color=body.color)
        if body.mesh is not None:
            builder.add_shape_mesh(index, mesh=newton.Mesh(body.mesh[0], body.mesh[1].ravel()), color=body.color)
    start = builder.particle_count
    for p in geometry.rest_positions.tolist():
        builder.add_particle(tuple(p), (0.0, 0.0, 0.0), 0.0, radius=PARTICLE_RADIUS_M)
    for s in geometry.surfaces:
        f = s.faces + start + s.rows.start
        builder.add_triangles(f[:, 0], f[:, 1], f[:, 2], color=s.color)


class EpisodeRenderer:
    """Renders episodes of one geometry layout: ``render(x, link_poses) -> {camera: (T, H, W, 3) uint8}``."""

    def __init__(self, geometry: EpisodeGeometry, cameras: Mapping[str, CameraConfig], device: str,
                 batch: int, shadows: bool) -> None:
        self.geometry = geometry
        self.cameras = dict(cameras)
        self.batch = int(batch)
        builder = newton.ModelBuilder()
        builder.add_shape_box(-1, xform=_transform((*geometry.table_center_m, 0.0, 0.0, 0.0, 1.0)),
                              hx=geometry.table_half_extents_m[0], hy=geometry.table_half_extents_m[1],
                              hz=geometry.table_half_extents_m[2], color=TABLE_COLOR)
        for _ in range(self.batch):
            builder.begin_world()
            _add_world(builder, geometry)
            builder.end_world()
        self.model = builder.finalize(device=device)
        self.state = self.model.state()
        config = SensorCamera.RenderConfig(enable_backface_culling=False, enable_shadows=shadows)
        self.sensor = SensorCamera(self.model, default_render_config=config, load_textures=False,
                                   default_clear_data=SensorCamera.ClearData(clear_color=_packed_rgba(BACKGROUND_RGB)))
        self.sensor.create_default_light(enable_shadows=shadows, direction=wp.vec3f(*_unit(LIGHT_DIRECTION)),
                                         color=LIGHT_COLOR)
        self.sensor.set_ambient_light(AMBIENT_SKY, AMBIENT_GROUND)
        self._rays = {n: SensorCamera.compute_camera_rays_pinhole(c.width, c.height, camera_fov=np.deg2rad(c.fov_deg),
                                                                   device=self.model.device)
                      for n, c in self.cameras.items()}
        self._images = {n: self.sensor.allocate_image_color(self.batch, c.width, c.height)
                        for n, c in self.cameras.items()}
        self.seconds = {n: 0.0 for n in self.cameras}  # SensorCamera time per camera (update + read back)

    def render(self, x: np.ndarray, link_poses: np.ndarray, where: str = "episode") -> dict[str, np.ndarray]:
        """Frames of every camera for object vertices x (T, N_e, 3) m and link poses (T, L_e, 7)."""
        g = self.geometry
        if x.ndim != 3 or x.shape[1:] != (g.num_vertices, 3) or link_poses.shape[1:] != (len(g.link_names), 7) \
                or len(x) != len(link_poses):
            raise ValueError(f"{where}: x {x.shape} / link_poses {link_poses.shape} do not match the geometry "
                             f"({g.num_vertices} vertices, {len(g.link_names)} links)")
        check_camera_links(self.cameras, g.link_names, where)
        poses = {n: camera_transforms(c, g.link_names, link_poses) for n, c in self.cameras.items()}
        columns = [b.column for b in g.bodies]
        frames = {n: np.empty((len(x), c.height, c.width, 3), np.uint8) for n, c in self.cameras.items()}
        for start in range(0, len(x), self.batch):
            ks = np.minimum(np.arange(start, start + self.batch), len(x) - 1)  # pad the last batch with its last frame
            n_valid = min(self.batch, len(x) - start)
            self.state.particle_q.assign(np.ascontiguousarray(x[ks].reshape(-1, 3), np.float32))
            if columns:
                self.state.body_q.assign(np.ascontiguousarray(link_poses[ks][:, columns].reshape(-1, 7), np.float32))
            self.model.bvh_refit_shapes(self.state)
            self.model.bvh_refit_particles(self.state)
            self.sensor.sync_deformable_meshes(self.state)
            for n in self.cameras:
                tic = time.perf_counter()
                tf = wp.array(poses[n][ks], dtype=wp.transformf, device=self.model.device)
                self.sensor.update(self.state, tf, self._rays[n], color_image=self._images[n], sync_deformables=False)
                rgba = self._images[n].numpy().view(np.uint8).reshape(self.batch, *frames[n].shape[1:3], 4)
                frames[n][start:start + n_valid] = rgba[:n_valid, ..., :3]
                self.seconds[n] += time.perf_counter() - tic
        return frames


def _unit(v: tuple[float, float, float]) -> tuple[float, float, float]:
    a = np.asarray(v, np.float64)
    return tuple(float(c) for c in a / np.linalg.norm(a))
