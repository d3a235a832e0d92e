"""Rim tasks: the right gripper pinches the top edge of the bag's front wall, then ...

- drag (6): ... drags the bag across the table (amplitude = distance, cell adds the direction);
- lift_body (10): ... lifts the bag by its body (amplitude = lift height) and holds.

Cell = (grasp position along the rim, bag yaw[, drag direction]); speed = TCP speed [m/s].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.scene import Scene
from wc.tasks.bag_geometry import bag_rows, ends_above, rim_grasp
from wc.tasks.base import EpisodeSpec, register_task
from wc.tasks.common import TaskProgram, check_range
from wc.tasks.lift_handle import hover_action, upright_bag
from wc.tasks.motion import ArmProgram, compose, tool_rotation


@dataclass(frozen=True)
class RimConfig:
    along_bins: tuple[float, ...]  # grasp position along the front rim, -1 .. 1 of its half-width
    yaw_bins_deg: tuple[float, ...]
    speed_range_m_s: tuple[float, float]
    amplitude_range_m: tuple[float, float]  # drag distance / lift height
    grasp_depth_m: float  # pinch this far below the rim
    hold_s: float

    def validate(self) -> None:
        check_range("speed_range_m_s", self.speed_range_m_s)
        check_range("amplitude_range_m", self.amplitude_range_m)


@dataclass(frozen=True)
class DragConfig(RimConfig):
    direction_bins_deg: tuple[float, ...] = (0.0, 90.0)  # drag direction, world yaw
    drag_height_m: float = 0.0  # the rim is raised this much while dragging


@dataclass(frozen=True)
class LiftBodyConfig(RimConfig):
    success_lift_m: float = 0.03


class RimTask(TaskProgram):
    BINS = ("along_bins", "yaw_bins_deg")

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        return upright_bag(scene, self.common, self.cell_values(spec.cell)["yaw_bins_deg"], rng)

    def _grasp(self, scene: Scene, x: np.ndarray, spec: EpisodeSpec):
        point, y, away = rim_grasp(scene, x, "right", self.cell_values(spec.cell)["along_bins"])
        point = point - np.array([0.0, 0.0, self.cfg.grasp_depth_m])
        return point, tool_rotation(y, away, self.common.approach_tilt_deg)

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        return hover_action(scene, self.common, [("right", *self._grasp(scene, initial.x, spec))], self.name)

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        c = self.common
        point, rot = self._grasp(scene, settled.x, spec)
        program = ArmProgram(scene, "right", start)
        program.move(point - c.approach_height_m * rot[:, 2], rot, c.open_m, speed=spec.speed)
        program.move(point, speed=spec.speed).grip(c.closed_m, c.close_s)
        program.move(point + self.displacement(spec), speed=spec.speed).hold(self.cfg.hold_s)
        self.finish(program, spec)
        return compose(scene, start, [program], frame_dt_s, c.ik, self.name)

    def displacement(self, spec: EpisodeSpec) -> np.ndarray:
        raise NotImplementedError

    def finish(self, program: ArmProgram, spec: EpisodeSpec) -> None:
        """What the gripper does after the hold (nothing by default)."""


@register_task("drag", DragConfig)
class Drag(RimTask):
    BINS = RimTask.BINS + ("direction_bins_deg",)

    def displacement(self, spec: EpisodeSpec) -> np.ndarray:
        yaw = np.deg2rad(self.cell_values(spec.cell)["direction_bins_deg"])
        return np.array([spec.amplitude * np.cos(yaw), spec.amplitude * np.sin(yaw), self.cfg.drag_height_m])

    def finish(self, program: ArmProgram, spec: EpisodeSpec) -> None:
        program.grip(self.common.open_m, self.common.close_s)
        program.move(program.position + np.array([0.0, 0.0, 0.04]), speed=spec.speed)

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_dragged' unless the bag's centre moved at least half the drag distance."""
        moved = np.linalg.norm(bag_rows(scene, x[-1]).mean(0)[:2] - bag_rows(scene, x[0]).mean(0)[:2])
        return None if moved >= 0.5 * spec.amplitude else "not_dragged"


@register_task("lift_body", LiftBodyConfig)
class LiftBody(RimTask):
    def displacement(self, spec: EpisodeSpec) -> np.ndarray:
        return np.array([0.0, 0.0, spec.amplitude])

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_lifted' unless the bag's lowest vertex ends success_lift_m above the table."""
        return ends_above(scene, x, self.cfg.success_lift_m, "not_lifted")
