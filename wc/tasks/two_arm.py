"""Two-arm tasks:

- lift_two_arms (9): each gripper pinches the handle nearer it; both lift together;
- support (14): the right gripper lifts the bag by its handle; the closed left gripper comes in
  horizontally under the hanging bag and pushes up into it (amplitude = the push);
- load_and_lift (15): a sphere rests inside the bag (two predicted objects); both arms lift it by
  the handles.

Cells and speeds as for the one-arm handle tasks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.scene import Scene
from wc.tasks.bag_geometry import bag_rows, ends_above
from wc.tasks.base import EpisodeSpec, register_task
from wc.tasks.lift_handle import HandleConfig, HandleTask, hover_action, upright_bag
from wc.tasks.motion import ArmProgram, compose, home_separation, tool_rotation


@dataclass(frozen=True)
class SupportConfig(HandleConfig):
    lift_m: float = 0.15  # right-arm lift before the left arm comes in
    support_start_height_m: float = 0.03  # left TCP height above the table when it slides in
    support_reach_m: float = 0.08  # horizontal travel of the left gripper towards the bag
    support_tilt_deg: float = 60.0  # left tool axis from vertical (90 = horizontal)


@dataclass(frozen=True)
class LoadConfig(HandleConfig):
    sphere_clearance_m: float = 0.005  # the sphere's lowest point above the bag's bottom at the start


class TwoHandleTask(HandleTask):
    """Both arms pinch their handles, then lift together by the amplitude."""

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        targets = [(side, *self._grasp(scene, initial.x, spec, side)[::3]) for side in ("left", "right")]
        return hover_action(scene, self.common, targets, self.name)

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        grasps = [self.approach(scene, settled, spec, start, side) for side in ("left", "right")]
        together = max(g[0].duration for g in grasps)
        for program, point, y, away in grasps:
            program.hold_until(together)
            self.lift(program, scene, point, y, away, spec.amplitude, spec.speed)
        ends = max(g[0].duration for g in grasps)
        for program, *_ in grasps:
            program.hold_until(ends).hold(self.cfg.hold_s)
        return compose(scene, start, [g[0] for g in grasps], frame_dt_s, self.common.ik, self.name)

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_lifted' unless every predicted object ends success_lift_m above the table."""
        return ends_above(scene, x, self.cfg.success_lift_m, "not_lifted", tuple(scene.objects))


@register_task("lift_two_arms", HandleConfig)
class LiftTwoArms(TwoHandleTask):
    pass


@register_task("load_and_lift", LoadConfig)
class LoadAndLift(TwoHandleTask):
    objects = ("bag", "sphere")

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        bag = upright_bag(scene, self.common, self.cell_values(spec.cell)["yaw_bins_deg"], rng).x
        bottom = bag[scene.objects["bag"].groups["bottom"]]
        sphere = scene.objects["sphere"].vertices
        centre = bottom.mean(0) + np.array([0.0, 0.0, self.cfg.sphere_clearance_m - sphere[:, 2].min()])
        x = np.concatenate([bag, sphere + centre]).astype(np.float32)
        return ObjectState(x, np.zeros_like(x))


@register_task("support", SupportConfig)
class Support(HandleTask):
    def _support(self, scene: Scene, x: np.ndarray, spec: EpisodeSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The left gripper's staging point (low, beside the bag's footprint), the point under the
        lifted bag and its tool rotation: the bag hangs below the right pinch once lifted."""
        cfg = self.cfg
        point, y, away, _ = self._grasp(scene, x, spec)
        top = point + np.array([0.0, 0.0, cfg.lift_m]) - cfg.lift_retract_m * away
        under = np.array([top[0], top[1], scene.table.top_z + cfg.support_start_height_m])
        inward = np.array([1.0, 0.0, 0.0]) if under[0] > scene.left_base[0] else np.array([-1.0, 0.0, 0.0])
        footprint = (bag_rows(scene, x) - under) @ inward
        staging = under + (footprint.min() - cfg.support_reach_m) * inward
        return staging, under, tool_rotation(home_separation(scene, "left"), inward, cfg.support_tilt_deg)

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        staging, _, rot = self._support(scene, initial.x, spec)
        action = hover_action(scene, self.common, [("right", *self._grasp(scene, initial.x, spec)[::3]),
                                                   ("left", staging + self.common.start_height_m * rot[:, 2], rot)],
                              self.name)
        action[6] = self.common.closed_m
        return action

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        right, point, y, away = self.approach(scene, settled, spec, start)
        self.lift(right, scene, point, y, away, self.cfg.lift_m, spec.speed)
        staging, under, _ = self._support(scene, settled.x, spec)
        left = ArmProgram(scene, "left", start).move(staging, seconds=right.duration)
        left.move(under, speed=spec.speed).move(under + np.array([0.0, 0.0, spec.amplitude]), speed=spec.speed)
        right.hold_until(left.duration)
        right.hold(self.cfg.hold_s)
        left.hold_until(right.duration)
        return compose(scene, start, [left, right], frame_dt_s, self.common.ik, self.name)

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_lifted' unless the bag ends off the table."""
        return ends_above(scene, x, self.cfg.success_lift_m, "not_lifted")
