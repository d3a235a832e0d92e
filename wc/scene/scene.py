"""The assembled scene: predicted objects, table, two PiPER arms, sample sets, cameras.

Built once from params (static description, like Newton's `Model`); the changing object state
and the prescribed inputs live elsewhere (`wc.dynamics`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from wc.scene.bag import make_bag
from wc.scene.config import CameraConfig, SceneConfig, TableConfig
from wc.scene.mesh import ObjectMesh
from wc.scene.piper import ARM_BODY_NAMES, arm_poses_from_action
from wc.scene.rigid import make_cube, make_sphere
from wc.scene.robot_geometry import LinkShape, link_surface_samples, piper_link_shapes
from wc.scene.table import TableSpec, table_env_samples
from wc.rotations import quat_multiply, quat_rotate

OBJECT_KINDS = {"bag": "cloth", "sphere": "rigid", "cube": "rigid"}


@dataclass(frozen=True)
class SampleSet:
    """Prescribed surface samples (controllable or environmental) fixed in one body's frame."""

    name: str
    body: str  # robot link (e.g. right_finger_a) or environment body (table)
    local_points: np.ndarray  # (M, 3) float32 [m]
    local_normals: np.ndarray  # (M, 3) float32, unit
    tag: int


@dataclass(frozen=True)
class HeldObject:
    """A rigid object held by the robot: prescribed, posed by its link (it is part of B_t, not S_t)."""

    mesh: ObjectMesh
    link: str  # robot body holding it, e.g. right_link6
    local_pose: np.ndarray  # (7,) object pose in the link frame


@dataclass
class Scene:
    objects: dict[str, ObjectMesh]  # predicted objects, in the order their vertices are concatenated
    table: TableConfig
    left_base: np.ndarray  # (7,) pos + quat xyzw
    right_base: np.ndarray
    link_names: tuple[str, ...]  # robot bodies driven by the action, columns of link_poses
    link_shapes: list[LinkShape]  # primitives per (unprefixed) link name
    samples: list[SampleSet]  # controllable (robot) then environmental (table) sample sets
    env_names: tuple[str, ...] = ("table",)
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
    home_q: tuple[float, ...] = ()
    idle_q: tuple[float, ...] = ()  # joints of an arm a task program does not move (empty: home_q)
    held: dict[str, HeldObject] = field(default_factory=dict)  # body name (held_<object>) -> held object

    @property
    def object_kinds(self) -> dict[str, str]:
        return {name: OBJECT_KINDS[name] for name in self.objects}

    @property
    def num_vertices(self) -> int:
        return sum(len(m.vertices) for m in self.objects.values())

    def vertex_slices(self) -> dict[str, slice]:
        """Rows of the concatenated state x (N_total, 3) that belong to each object."""
        out, start = {}, 0
        for name, mesh in self.objects.items():
            out[name] = slice(start, start + len(mesh.vertices))
            start += len(mesh.vertices)
        return out

    def env_poses(self) -> np.ndarray:
        """(E, 7) poses of the environment bodies (the table is static)."""
        c = np.asarray(self.table.center_m, np.float32)
        return np.array([[*c, 0.0, 0.0, 0.0, 1.0]], np.float32)

    def link_poses(self, action: np.ndarray) -> np.ndarray:
        """World poses (..., L, 7) of the robot bodies, then the held objects, for actions (..., 14)."""
        a = torch.as_tensor(np.asarray(action, np.float32))
        poses = arm_poses_from_action(a, torch.as_tensor(self.left_base), torch.as_tensor(self.right_base)).numpy()
        held = []
        for obj in self.held.values():
            link = poses[..., self.link_names.index(obj.link), :]
            pos = link[..., :3] + quat_rotate(link[..., 3:], np.broadcast_to(obj.local_pose[:3], link[..., :3].shape))
            held.append(np.concatenate([pos, quat_multiply(link[..., 3:], obj.local_pose[3:])], axis=-1)[..., None, :])
        return np.concatenate([poses, *held], axis=-2).astype(np.float32)

    def home_action(self, left_opening_m: float = 0.0, right_opening_m: float = 0.0) -> np.ndarray:
        """(14,) action holding both arms at the home posture."""
        q = np.asarray(self.home_q, np.float32)
        return np.concatenate([q, [left_opening_m], q, [right_opening_m]]).astype(np.float32)


def yaw_pose(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    """(7,) pose at (x, y, z) rotated about world z."""
    half = np.deg2rad(yaw_deg) / 2.0
    return np.array([x, y, z, 0.0, 0.0, np.sin(half), np.cos(half)], np.float32)


def build_objects(cfg: SceneConfig, names: Sequence[str]) -> dict[str, ObjectMesh]:
    """Rest meshes of the predicted objects a task needs, in a fixed order."""
    makers = {
        "bag": lambda: make_bag(cfg.bag.target_vertices, cfg.bag.width_m, cfg.bag.depth_m, cfg.bag.height_m,
                                cfg.bag.handle_width_m, cfg.bag.handle_rise_m, cfg.bag.tag),
        "sphere": lambda: make_sphere(cfg.sphere.radius_m, cfg.sphere.target_vertices, cfg.sphere.tag),
        "cube": lambda: make_cube(cfg.cube.half_extent_m, cfg.cube.target_vertices, cfg.cube.tag),
    }
    unknown = [n for n in names if n not in makers]
    if unknown:
        raise ValueError(f"unknown object {unknown[0]!r}; known objects: {sorted(makers)}")
    return {name: makers[name]() for name in makers if name in names}


def build_scene(cfg: SceneConfig, object_names: Sequence[str] = ("bag",),
                held: dict[str, tuple[str, Sequence[float]]] | None = None) -> Scene:
    """Assemble the scene with only the predicted objects a task needs, plus objects the robot holds
    (`held`: object name -> (link, local pose (7,))), whose surface vertices become controllable samples."""
    robot = cfg.robot
    samples = []
    local = link_surface_samples(robot.sample_spacing_m, robot.sampled_links)
    link_index = {name: k for k, name in enumerate(ARM_BODY_NAMES[: len(ARM_BODY_NAMES) // 2])}
    for side, base_tag in (("left", robot.left_tag), ("right", robot.right_tag)):
        for link, (points, normals) in local.items():
            samples.append(SampleSet(f"{side}_{link}", f"{side}_{link}", points, normals,
                                     base_tag + link_index[f"left_{link}"]))
    held_objects = {}
    for name, (link, local_pose) in (held or {}).items():
        if link not in ARM_BODY_NAMES:
            raise ValueError(f"held {name!r}: unknown link {link!r}; known: {list(ARM_BODY_NAMES)}")
        mesh = build_objects(cfg, [name])[name]
        held_objects[f"held_{name}"] = HeldObject(mesh, link, np.asarray(local_pose, np.float32))
        normals = mesh.to_trimesh().vertex_normals.astype(np.float32)
        samples.append(SampleSet(f"held_{name}", f"held_{name}", mesh.vertices, normals, mesh.tag))
    table = cfg.table
    spec = TableSpec(np.asarray(table.center_m, np.float32), np.asarray(table.half_extents_m, np.float32))
    points, normals = table_env_samples(spec, np.asarray(table.sample_region_center_m, np.float32),
                                        np.asarray(table.sample_region_half_m, np.float32), table.sample_spacing_m)
    samples.append(SampleSet("table", "table", points, normals, table.tag))
    return Scene(
        objects=build_objects(cfg, object_names),
        table=table,
        left_base=yaw_pose(*robot.left_base_xyz_yaw_deg),
        right_base=yaw_pose(*robot.right_base_xyz_yaw_deg),
        link_names=tuple(ARM_BODY_NAMES) + tuple(held_objects),
        link_shapes=piper_link_shapes(),
        samples=samples,
        cameras=dict(cfg.cameras),
        home_q=tuple(robot.home_q),
        idle_q=tuple(robot.idle_q or robot.home_q),
        held=held_objects,
    )
