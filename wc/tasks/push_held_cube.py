"""Task 5, push-held-cube: the right gripper holds a cube (prescribed, part of the robot) and pushes
the standing bag across the table.

Cell = (contact height, lateral offset, bag yaw); amplitude = push distance past first contact [m];
speed = TCP speed [m/s].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.piper import TCP_IN_LINK6_M
from wc.scene.scene import Scene
from wc.tasks.bag_geometry import bag_rows
from wc.tasks.base import EpisodeSpec, register_task
from wc.tasks.common import TaskProgram, check_range
from wc.tasks.lift_handle import hover_action, upright_bag
from wc.tasks.motion import ArmProgram, arm_base, compose, home_separation, radial, tool_rotation


@dataclass(frozen=True)
class PushHeldCubeConfig:
    height_bins_m: tuple[float, ...]  # cube centre above the table
    lateral_bins_m: tuple[float, ...]  # offset across the push direction
    yaw_bins_deg: tuple[float, ...]
    speed_range_m_s: tuple[float, float]
    amplitude_range_m: tuple[float, float]  # push distance past the bag's near face
    gap_m: float  # free travel before the cube reaches the bag
    hold_s: float

    def validate(self) -> None:
        check_range("speed_range_m_s", self.speed_range_m_s)
        check_range("amplitude_range_m", self.amplitude_range_m)


def held_at_tcp(link: str = "right_link6") -> tuple[str, np.ndarray]:
    """(link, local pose) of an object centred between the pads, axes along link6's."""
    return link, np.array([*TCP_IN_LINK6_M, 0.0, 0.0, 0.0, 1.0], np.float32)


@register_task("push_held_cube", PushHeldCubeConfig)
class PushHeldCube(TaskProgram):
    objects = ("bag",)
    BINS = ("height_bins_m", "lateral_bins_m", "yaw_bins_deg")

    def held(self) -> dict[str, tuple[str, np.ndarray]]:
        return {"cube": held_at_tcp()}

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        return upright_bag(scene, self.common, self.cell_values(spec.cell)["yaw_bins_deg"], rng)

    def _path(self, scene: Scene, x: np.ndarray, spec: EpisodeSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Start point, end point and TCP rotation of the push."""
        c = self.cell_values(spec.cell)
        xb = bag_rows(scene, x)
        centre = xb.mean(0)
        u = radial(scene, "right", centre)  # push away from the arm's base
        lateral = np.cross(np.array([0.0, 0.0, 1.0]), u)
        z = scene.table.top_z + c["height_bins_m"]
        band = xb[np.abs(xb[:, 2] - z) < 0.03]
        base = arm_base(scene, "right")[:3]
        near = ((band if len(band) else xb) - base) @ u
        half = float(np.abs(scene.held["held_cube"].mesh.vertices).max()) if "held_cube" in scene.held else 0.03
        face = base + near.min() * u
        line = np.array([centre[0], centre[1], z]) + c["lateral_bins_m"] * lateral
        line = line + ((face - line) @ u) * u  # on the near face, at the cell's height and offset
        start = line - (half * np.sqrt(3) + self.cfg.gap_m) * u
        rot = tool_rotation(home_separation(scene, "right"), u, self.common.approach_tilt_deg)
        return start, line + spec.amplitude * u, rot

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        start, _, rot = self._path(scene, initial.x, spec)
        action = hover_action(scene, self.common, [("right", start, rot)], self.name)
        action[13] = self._grip_opening(scene)
        return action

    def _grip_opening(self, scene: Scene) -> float:
        """Pads on the cube's faces."""
        return float(2 * np.abs(scene.held["held_cube"].mesh.vertices).max())

    def actions(self, scene, settled, spec, start, frame_dt_s) -> np.ndarray:
        p0, p1, rot = self._path(scene, settled.x, spec)
        program = ArmProgram(scene, "right", start).move(p0, rot, speed=spec.speed)
        program.move(p1, speed=spec.speed).hold(self.cfg.hold_s)
        program.move(p1 - 0.04 * rot[:, 2], speed=spec.speed)
        return compose(scene, start, [program], frame_dt_s, self.common.ik, self.name)
