"""Falling objects, the robot idle at home:

- bag_drop (1): the bag falls onto the table and settles; cell = (roll, yaw) of the falling bag;
- sphere_drop (2) / cube_drop (3): a free sphere / cube falls onto the bag lying on the table;
  cell = (landing offset across the bag, along it[, cube roll]).

amplitude = drop height [m] (bag: bottom above the table; rigid: above the bag's top), speed =
initial downward speed [m/s].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from wc.dynamics import ObjectState
from wc.scene.scene import Scene
from wc.tasks.bag_geometry import placed, top_surface_point
from wc.tasks.base import EpisodeSpec, register_task
from wc.tasks.common import TaskProgram, check_range


@dataclass(frozen=True)
class BagDropConfig:
    roll_bins_deg: tuple[float, ...]  # 0 upright, 90 lying on its front face
    yaw_bins_deg: tuple[float, ...]
    speed_range_m_s: tuple[float, float]  # initial downward speed
    amplitude_range_m: tuple[float, float]  # bottom above the table
    duration_s: float

    def validate(self) -> None:
        check_range("speed_range_m_s", self.speed_range_m_s, low_may_be_zero=True)
        check_range("amplitude_range_m", self.amplitude_range_m)


@dataclass(frozen=True)
class ObjectDropConfig:
    offset_x_bins_m: tuple[float, ...]  # landing point relative to the bag's centre
    offset_y_bins_m: tuple[float, ...]
    roll_bins_deg: tuple[float, ...]  # initial orientation of the falling object about x
    bag_roll_deg: float  # the bag under it: 90 = lying on its front face
    speed_range_m_s: tuple[float, float]
    amplitude_range_m: tuple[float, float]  # lowest object point above the bag's top
    duration_s: float

    def validate(self) -> None:
        check_range("speed_range_m_s", self.speed_range_m_s, low_may_be_zero=True)
        check_range("amplitude_range_m", self.amplitude_range_m)


def idle(scene: Scene, start: np.ndarray, seconds: float, frame_dt_s: float) -> np.ndarray:
    """The robot holds `start` for `seconds`."""
    return np.repeat(np.asarray(start, np.float32)[None], 1 + int(np.ceil(seconds / frame_dt_s)), axis=0)


def lying_bag(scene: Scene, common, roll_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Bag vertices rolled by roll_deg (90 = on its front face) just above the table, jittered."""
    return placed(scene.objects["bag"].vertices, 0.0, roll_deg, common.bag_centre(rng),
                  scene.table.top_z + common.drop_height_m)


@register_task("bag_drop", BagDropConfig)
class BagDrop(TaskProgram):
    BINS = ("roll_bins_deg", "yaw_bins_deg")
    settle = False

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        c = self.cell_values(spec.cell)
        x = placed(scene.objects["bag"].vertices, c["yaw_bins_deg"], c["roll_bins_deg"], self.common.bag_centre(rng),
                   scene.table.top_z + spec.amplitude)
        v = np.zeros_like(x)
        v[:, 2] = -spec.speed
        return ObjectState(x, v)

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        return scene.home_action()

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        return idle(scene, start, self.cfg.duration_s, frame_dt_s)


class ObjectDrop(TaskProgram):
    """A rigid object parked on the table while the bag settles, then dropped onto the bag."""

    BINS = ("offset_x_bins_m", "offset_y_bins_m", "roll_bins_deg")
    RIGID: str

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        bag = lying_bag(scene, self.common, self.cfg.bag_roll_deg, rng)
        rigid = scene.objects[self.RIGID].vertices
        parked = rigid + np.array([0.0, 0.3, scene.table.top_z - rigid[:, 2].min() + 0.001])  # out of the way
        x = np.concatenate([bag, parked]).astype(np.float32)
        return ObjectState(x, np.zeros_like(x))

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        return scene.home_action()

    def prepare(self, scene: Scene, settled: ObjectState, spec: EpisodeSpec, rng: np.random.Generator
                ) -> ObjectState:
        c = self.cell_values(spec.cell)
        rows = scene.vertex_slices()[self.RIGID]
        target = top_surface_point(scene, settled.x, np.array([c["offset_x_bins_m"], c["offset_y_bins_m"]]))
        body = Rotation.from_euler("xz", [c["roll_bins_deg"], rng.uniform(0, 360)], degrees=True)
        local = body.apply(scene.objects[self.RIGID].vertices.astype(np.float64))
        x, v = settled.x.copy(), settled.v.copy()
        x[rows] = local + target + np.array([0.0, 0.0, spec.amplitude - local[:, 2].min()])
        v[rows] = np.array([0.0, 0.0, -spec.speed])
        return ObjectState(x, v)

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        return idle(scene, start, self.cfg.duration_s, frame_dt_s)


@register_task("sphere_drop", ObjectDropConfig)
class SphereDrop(ObjectDrop):
    objects = ("bag", "sphere")
    RIGID = "sphere"


@register_task("cube_drop", ObjectDropConfig)
class CubeDrop(ObjectDrop):
    objects = ("bag", "cube")
    RIGID = "cube"
