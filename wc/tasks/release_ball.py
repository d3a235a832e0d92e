"""Task 16, release-ball-into-bag: the right gripper holds a ball (prescribed, part of the robot)
over the standing bag's opening and lets go; from the frame its gripper opens the ball is a
predicted object (the paper's S_t / B_t switch, stored as the episode attr `handoff`).

Cell = (release point along the opening, bag yaw); amplitude = ball's lowest point above the rim
[m]; speed = TCP speed [m/s].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.scene import Scene
from wc.tasks.bag_geometry import bag_rows, width_axes
from wc.tasks.base import EpisodeSpec, register_task
from wc.tasks.common import TaskProgram, check_range
from wc.tasks.lift_handle import hover_action, upright_bag
from wc.tasks.motion import ArmProgram, compose, home_separation, radial, tool_rotation
from wc.tasks.push_held_cube import held_at_tcp


@dataclass(frozen=True)
class ReleaseBallConfig:
    along_bins: tuple[float, ...]  # release point along the opening's width, -1 .. 1 of its half-width
    yaw_bins_deg: tuple[float, ...]
    speed_range_m_s: tuple[float, float]
    amplitude_range_m: tuple[float, float]  # ball's lowest point above the rim at release
    carry_m: float  # the ball is carried this far (towards the opening) before release
    fall_s: float  # recorded after the gripper opened

    def validate(self) -> None:
        check_range("speed_range_m_s", self.speed_range_m_s)
        check_range("amplitude_range_m", self.amplitude_range_m)


@register_task("release_ball_into_bag", ReleaseBallConfig)
class ReleaseBallIntoBag(TaskProgram):
    objects = ("bag", "sphere")
    BINS = ("along_bins", "yaw_bins_deg")
    handoff = ("sphere",)

    def held(self) -> dict[str, tuple[str, np.ndarray]]:
        return {"sphere": held_at_tcp()}

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        return upright_bag(scene, self.common, self.cell_values(spec.cell)["yaw_bins_deg"], rng)

    def _release(self, scene: Scene, x: np.ndarray, spec: EpisodeSpec) -> tuple[np.ndarray, np.ndarray]:
        """TCP (= ball centre) at release, and the tool rotation."""
        xb = bag_rows(scene, x)
        centre, width, _ = width_axes(scene, xb)
        half_w = 0.5 * np.ptp((xb[scene.objects["bag"].groups["rim"]] - centre) @ width)
        radius = float(np.linalg.norm(scene.held["held_sphere"].mesh.vertices, axis=1).max())
        rim_top = xb[scene.objects["bag"].groups["rim"], 2].max()
        point = centre + 0.5 * self.cell_values(spec.cell)["along_bins"] * half_w * width
        point[2] = rim_top + spec.amplitude + radius
        rot = tool_rotation(home_separation(scene, "right"), radial(scene, "right", point),
                            self.common.approach_tilt_deg)
        return point, rot

    def _grip_opening(self, scene: Scene) -> float:
        return float(2 * np.linalg.norm(scene.held["held_sphere"].mesh.vertices, axis=1).max())

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        point, rot = self._release(scene, initial.x, spec)
        back = point - self.cfg.carry_m * radial(scene, "right", point)
        action = hover_action(scene, self.common, [("right", back + self.common.start_height_m * rot[:, 2], rot)],
                              self.name)
        action[13] = self._grip_opening(scene)
        return action

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        point, rot = self._release(scene, settled.x, spec)
        program = ArmProgram(scene, "right", start).move(point, rot, speed=spec.speed).hold(0.1)
        program.grip(self.common.open_m, self.common.close_s)
        program.move(program.position - 0.05 * rot[:, 2], speed=spec.speed).hold(self.cfg.fall_s)
        return compose(scene, start, [program], frame_dt_s, self.common.ik, self.name)
