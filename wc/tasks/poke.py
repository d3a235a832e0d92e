"""Task 4, poke: the closed right gripper presses into the bag lying on the table and withdraws.

Cell = (press point relative to the bag's centre, x and y); amplitude = press depth below the
bag's top surface [m] along the approach; speed = TCP speed [m/s].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.scene import Scene
from wc.tasks.bag_geometry import top_surface_point
from wc.tasks.base import EpisodeSpec, register_task
from wc.tasks.common import TaskProgram, check_range
from wc.tasks.drops import lying_bag
from wc.tasks.lift_handle import hover_action
from wc.tasks.motion import ArmProgram, compose, home_separation, radial, tool_rotation


@dataclass(frozen=True)
class PokeConfig:
    offset_x_bins_m: tuple[float, ...]
    offset_y_bins_m: tuple[float, ...]
    bag_roll_deg: float  # 90 = lying on its front face
    speed_range_m_s: tuple[float, float]
    amplitude_range_m: tuple[float, float]  # press depth
    hold_s: float  # pressed this long

    def validate(self) -> None:
        check_range("speed_range_m_s", self.speed_range_m_s)
        check_range("amplitude_range_m", self.amplitude_range_m)


@register_task("poke", PokeConfig)
class Poke(TaskProgram):
    BINS = ("offset_x_bins_m", "offset_y_bins_m")

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        x = lying_bag(scene, self.common, self.cfg.bag_roll_deg, rng)
        return ObjectState(x, np.zeros_like(x))

    def _target(self, scene: Scene, x: np.ndarray, spec: EpisodeSpec) -> tuple[np.ndarray, np.ndarray]:
        c = self.cell_values(spec.cell)
        point = top_surface_point(scene, x, np.array([c["offset_x_bins_m"], c["offset_y_bins_m"]]))
        rot = tool_rotation(home_separation(scene, "right"), radial(scene, "right", point),
                            self.common.approach_tilt_deg)
        return point, rot

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        action = hover_action(scene, self.common, [("right", *self._target(scene, initial.x, spec))], self.name)
        action[13] = self.common.closed_m
        return action

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        point, rot = self._target(scene, settled.x, spec)
        pre = point - self.common.approach_height_m * rot[:, 2]
        program = ArmProgram(scene, "right", start).move(pre, rot, speed=spec.speed)
        program.move(point + spec.amplitude * rot[:, 2], speed=spec.speed).hold(self.cfg.hold_s)
        program.move(pre, speed=spec.speed)
        return compose(scene, start, [program], frame_dt_s, self.common.ik, self.name)
