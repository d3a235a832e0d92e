"""One-arm handle tasks: the right gripper pinches the handle nearer it, then ...

- grasp_handle (7): ... holds it without lifting (amplitude = the commanded closed opening);
- lift_handle (8, the policy task "right grasp and lift"): ... lifts by amplitude and holds;
- place (11): ... lifts, carries the bag sideways, sets it down and lets go;
- release_drop (12): ... lifts by amplitude and lets go;
- shake (13): ... lifts and oscillates horizontally (amplitude, peak speed).

Coverage cell = (grasp depth below the handle's apex, position across the strap, initial bag yaw
[, task-specific bin]); speed = TCP speed [m/s].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.scene import Scene
from wc.tasks.bag_geometry import bag_rows, ends_above, handle_grasp, lowest_height, placed
from wc.tasks.base import EpisodeSpec, register_task
from wc.tasks.common import TaskProgram, check_range
from wc.tasks.motion import ArmProgram, compose, reach, tool_rotation


@dataclass(frozen=True)
class HandleConfig:
    grasp_depth_bins_m: tuple[float, ...]  # pinch this far below the handle apex
    grasp_across_bins: tuple[float, ...]  # position across the strap width, 0..1
    yaw_bins_deg: tuple[float, ...]  # initial bag yaw about z
    speed_range_m_s: tuple[float, float]  # TCP speed
    amplitude_range_m: tuple[float, float]  # lift height (grasp_handle: commanded closed opening)
    lift_tilt_deg: float  # tilt at the top of the lift (the arm reaches higher with more tilt)
    lift_retract_m: float  # the lift also pulls back this far towards the arm's base
    hold_s: float
    success_lift_m: float  # lifted if the bag's lowest vertex ends this far above the table

    def validate(self) -> None:
        check_range("speed_range_m_s", self.speed_range_m_s)
        check_range("amplitude_range_m", self.amplitude_range_m, low_may_be_zero=True)
        if self.hold_s < 0:
            raise ValueError("hold_s must be non-negative")


@dataclass(frozen=True)
class PlaceConfig(HandleConfig):
    place_direction_bins_deg: tuple[float, ...] = (90.0,)  # carry direction, world yaw
    place_distance_m: float = 0.06
    set_down_height_m: float = 0.01  # lowest bag point above the table when releasing


@dataclass(frozen=True)
class ReleaseDropConfig(HandleConfig):
    fall_s: float = 0.6  # recorded after the gripper opened


@dataclass(frozen=True)
class ShakeConfig(HandleConfig):
    shake_axis_bins_deg: tuple[float, ...] = (0.0, 90.0)  # oscillation direction, world yaw
    lift_m: float = 0.1
    cycles: float = 2.0
    lift_speed_m_s: float = 0.08  # the lift before the oscillation: a slow lift lets the strap creep out of the pads


class HandleTask(TaskProgram):
    """Approach, pinch and (in subclasses) move the right-arm handle."""

    SIDE: ClassVar[str] = "right"
    BINS = ("grasp_depth_bins_m", "grasp_across_bins", "yaw_bins_deg")

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        return upright_bag(scene, self.common, self.cell_values(spec.cell)["yaw_bins_deg"], rng)

    def _grasp(self, scene: Scene, x: np.ndarray, spec: EpisodeSpec, side: str | None = None):
        c = self.cell_values(spec.cell)
        side = side or self.SIDE
        point, y, away = handle_grasp(scene, x, side, c["grasp_depth_bins_m"], c["grasp_across_bins"])
        return point, y, away, tool_rotation(y, away, self.common.approach_tilt_deg)

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        return hover_action(scene, self.common, [(self.SIDE, *self._grasp(scene, initial.x, spec)[::3])],
                            self.name)

    def approach(self, scene: Scene, state: ObjectState, spec: EpisodeSpec, start: np.ndarray,
                 side: str | None = None) -> tuple[ArmProgram, np.ndarray, np.ndarray, np.ndarray]:
        """Program: pre-grasp, descend along the approach axis, close. Returns it with the grasp
        point, pad axis and away direction."""
        side = side or self.SIDE
        c = self.common
        point, y, away, rot = self._grasp(scene, state.x, spec, side)
        speed = min(spec.speed, max(self.speed_range()))
        program = ArmProgram(scene, side, start)
        program.move(point - c.approach_height_m * rot[:, 2], rot, c.open_m, speed=speed)
        program.move(point, speed=speed).grip(c.closed_m, c.close_s)
        return program, point, y, away

    def lift(self, program: ArmProgram, scene: Scene, point: np.ndarray, y: np.ndarray, away: np.ndarray,
             height: float, speed: float) -> np.ndarray:
        """Append a lift by `height` (with the configured retract and tilt); returns the top point."""
        top = point + np.array([0.0, 0.0, height]) - self.cfg.lift_retract_m * away
        program.move(top, tool_rotation(y, away, self.cfg.lift_tilt_deg), speed=speed)
        return top

    def actions(self, scene: Scene, settled: ObjectState, spec: EpisodeSpec, start: np.ndarray,
                frame_dt_s: float) -> np.ndarray:
        program, point, y, away = self.approach(scene, settled, spec, start)
        self.after_grasp(program, scene, point, y, away, spec, frame_dt_s)
        return compose(scene, start, [program], frame_dt_s, self.common.ik, self.name)

    def after_grasp(self, program: ArmProgram, scene: Scene, point: np.ndarray, y: np.ndarray,
                    away: np.ndarray, spec: EpisodeSpec, frame_dt_s: float) -> None:
        raise NotImplementedError


def upright_bag(scene: Scene, common, yaw_deg: float, rng: np.random.Generator) -> ObjectState:
    """The bag standing on the table (a little above it), yawed, jittered in xy."""
    x = placed(scene.objects["bag"].vertices, yaw_deg, 0.0, common.bag_centre(rng),
               scene.table.top_z + common.drop_height_m)
    return ObjectState(x, np.zeros_like(x))


def hover_action(scene: Scene, common, targets: list[tuple[str, np.ndarray, np.ndarray]], task: str) -> np.ndarray:
    """Each listed arm's TCP `start_height_m` back along the approach from its target point, gripper open: (side,
    point, rotation) per arm; an arm not listed at the scene's idle posture (scene.robot.idle_q, default home)."""
    action = scene.home_action()
    action[0:6] = action[7:13] = np.asarray(scene.idle_q or scene.home_q, np.float32)
    for side, point, rot in targets:
        cols, opening = (slice(7, 13), 13) if side == "right" else (slice(0, 6), 6)
        action[cols] = reach(scene, side, point - common.start_height_m * rot[:, 2], rot, common.ik, task)
        action[opening] = common.open_m
    return action


@register_task("grasp_handle", HandleConfig)
class GraspHandle(HandleTask):
    def after_grasp(self, program, scene, point, y, away, spec, frame_dt_s) -> None:
        program.grip(spec.amplitude, self.common.close_s).hold(self.cfg.hold_s)


@register_task("lift_handle", HandleConfig)
class LiftHandle(HandleTask):
    def after_grasp(self, program, scene, point, y, away, spec, frame_dt_s) -> None:
        self.lift(program, scene, point, y, away, spec.amplitude, spec.speed)
        program.hold(self.cfg.hold_s)

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_lifted' unless the bag's lowest vertex is success_lift_m above the table at the end."""
        return ends_above(scene, x, self.cfg.success_lift_m, "not_lifted")


@register_task("place", PlaceConfig)
class Place(HandleTask):
    BINS = HandleTask.BINS + ("place_direction_bins_deg",)

    def after_grasp(self, program, scene, point, y, away, spec, frame_dt_s) -> None:
        cfg = self.cfg
        top = self.lift(program, scene, point, y, away, spec.amplitude, spec.speed)
        yaw = np.deg2rad(self.cell_values(spec.cell)["place_direction_bins_deg"])
        shift = cfg.place_distance_m * np.array([np.cos(yaw), np.sin(yaw), 0.0])
        program.move(top + shift, speed=spec.speed)
        program.move(point + shift + np.array([0.0, 0.0, cfg.set_down_height_m]) - cfg.lift_retract_m * away,
                     speed=spec.speed)
        program.grip(self.common.open_m, self.common.close_s)
        program.move(program.position + np.array([0.0, 0.0, 0.04]), speed=spec.speed).hold(cfg.hold_s)

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_placed' unless the bag ends on the table, moved at least half the carry distance."""
        moved = np.linalg.norm(bag_rows(scene, x[-1]).mean(0)[:2] - bag_rows(scene, x[0]).mean(0)[:2])
        on_table = lowest_height(scene, x[-1:])[0] < 0.02
        return None if on_table and moved >= 0.5 * self.cfg.place_distance_m else "not_placed"


@register_task("release_drop", ReleaseDropConfig)
class ReleaseDrop(HandleTask):
    def after_grasp(self, program, scene, point, y, away, spec, frame_dt_s) -> None:
        self.lift(program, scene, point, y, away, spec.amplitude, spec.speed)
        program.hold(0.2).grip(self.common.open_m, self.common.close_s)
        program.move(program.position - 0.03 * away, seconds=0.2).hold(self.cfg.fall_s)

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_dropped' unless the bag was lifted and then lies on the table at the end."""
        heights = lowest_height(scene, x)
        return None if heights.max() >= self.cfg.success_lift_m and heights[-1] < 0.02 else "not_dropped"


@register_task("shake", ShakeConfig)
class Shake(HandleTask):
    BINS = HandleTask.BINS + ("shake_axis_bins_deg",)

    def after_grasp(self, program, scene, point, y, away, spec, frame_dt_s) -> None:
        cfg = self.cfg
        top = self.lift(program, scene, point, y, away, cfg.lift_m, cfg.lift_speed_m_s)
        yaw = np.deg2rad(self.cell_values(spec.cell)["shake_axis_bins_deg"])
        axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        omega = spec.speed / spec.amplitude  # peak TCP speed = amplitude * omega
        for t in np.arange(1, int(np.ceil(cfg.cycles * 2 * np.pi / omega / frame_dt_s)) + 1) * frame_dt_s:
            program.move(top + spec.amplitude * np.sin(omega * t) * axis, seconds=frame_dt_s)
        program.move(top, speed=cfg.lift_speed_m_s).hold(cfg.hold_s)

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'dropped' unless the bag still hangs success_lift_m above the table at the end."""
        return ends_above(scene, x, self.cfg.success_lift_m, "dropped")
