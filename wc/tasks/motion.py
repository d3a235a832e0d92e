"""Motion programs: timed TCP legs of one or both arms -> frame-by-frame 14-D actions by IK.

A task describes what each gripper does as straight-line legs of its tool centre point (position
linear, rotation slerped, opening linear); `compose` samples every leg on the frame clock and
solves IK leg by leg, warm-started from the previous leg, so the arm moves smoothly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from wc.scene.ik import solve_tool_ik
from wc.scene.piper import tool_pose
from wc.scene.scene import Scene
from wc.tasks.base import InfeasibleEpisode

ARM_COLUMNS = {"left": (slice(0, 6), 6), "right": (slice(7, 13), 13)}  # joints, opening in the action
ROTATION_LEVER_M = 0.1  # a leg's rotation counts as this lever arm times its angle of travel


@dataclass(frozen=True)
class IKSettings:
    iterations: int
    tolerance_m: float  # a plan whose IK misses by more is infeasible (a jerky arm would shake the grip)
    tolerance_rad: float


def tool_rotation(separation: np.ndarray, away: np.ndarray, tilt_deg: float) -> np.ndarray:
    """TCP rotation (3, 3) [x, y = pad separation, z = approach]: the approach points down, tilted by
    tilt_deg towards the horizontal `away` (90 = horizontal); the pads separate along `separation`
    made normal to the approach."""
    tilt = np.deg2rad(tilt_deg)
    z = -np.cos(tilt) * np.array([0.0, 0.0, 1.0]) + np.sin(tilt) * np.asarray(away, np.float64)
    y = np.asarray(separation, np.float64) - (separation @ z) * z
    y /= np.linalg.norm(y)
    return np.stack([np.cross(y, z), y, z], axis=1)


def arm_base(scene: Scene, side: str) -> np.ndarray:
    return scene.right_base if side == "right" else scene.left_base


def radial(scene: Scene, side: str, point: np.ndarray) -> np.ndarray:
    """Unit horizontal direction from an arm's base towards `point` (the arm tilts its tool most
    easily in its own vertical plane)."""
    d = np.asarray(point, np.float64) - arm_base(scene, side)[:3]
    d[2] = 0.0
    n = np.linalg.norm(d)
    return d / n if n > 1e-6 else np.array([1.0, 0.0, 0.0])


def home_separation(scene: Scene, side: str) -> np.ndarray:
    """The pad separation axis of an arm at home (pads are symmetric: prefer the sign needing least roll)."""
    from wc.rotations import quat_rotate

    return quat_rotate(arm_base(scene, side)[3:], np.array([0.0, 1.0, 0.0]))


def facing(separation: np.ndarray, scene: Scene, side: str) -> np.ndarray:
    """`separation` (3,) flipped, if needed, to agree with the arm's home pad axis."""
    s = np.asarray(separation, np.float64)
    return s if s @ home_separation(scene, side) >= 0 else -s


class ArmProgram:
    """Timed legs of one arm's TCP, starting where the arm is in `start_action`."""

    def __init__(self, scene: Scene, side: str, start_action: np.ndarray):
        if side not in ARM_COLUMNS:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        self.side = side
        joints, opening = ARM_COLUMNS[side]
        self.start_q = np.asarray(start_action[joints], np.float32)
        pose = tool_pose(torch.as_tensor(self.start_q), float(start_action[opening]),
                         torch.as_tensor(arm_base(scene, side))).numpy().astype(np.float64)
        self.position, self.rotation = pose[:3], Rotation.from_quat(pose[3:]).as_matrix()
        self.opening = float(start_action[opening])
        self.start = (self.position, self.rotation, self.opening)
        self.legs: list[tuple[np.ndarray, np.ndarray, float, float]] = []  # (position, rotation, opening, s)

    @property
    def duration(self) -> float:
        return sum(leg[3] for leg in self.legs)

    def move(self, position: np.ndarray | None = None, rotation: np.ndarray | None = None,
             opening: float | None = None, *, speed: float | None = None, seconds: float | None = None
             ) -> ArmProgram:
        """A straight leg to (position, rotation, opening), each defaulting to the current one; it
        lasts `seconds`, or as long as moving at `speed` m/s (the rotation at speed / 0.1 m) takes."""
        position = self.position if position is None else np.asarray(position, np.float64)
        rotation = self.rotation if rotation is None else np.asarray(rotation, np.float64)
        opening = self.opening if opening is None else float(opening)
        if seconds is None:
            if speed is None or speed <= 0:
                raise ValueError("a leg needs a positive speed or a duration in seconds")
            angle = Rotation.from_matrix(rotation @ self.rotation.T).magnitude()
            seconds = max(np.linalg.norm(position - self.position), ROTATION_LEVER_M * angle) / speed
        self.legs.append((position, rotation, opening, float(seconds)))
        self.position, self.rotation, self.opening = position, rotation, opening
        return self

    def grip(self, opening: float, seconds: float) -> ArmProgram:
        """Open or close the gripper in place."""
        return self.move(opening=opening, seconds=seconds)

    def hold(self, seconds: float) -> ArmProgram:
        return self.move(seconds=seconds)

    def hold_until(self, t: float) -> ArmProgram:
        """Stay put until time t (s) of the program, if it has not reached it yet."""
        return self.hold(t - self.duration) if t > self.duration else self

    def sample(self, times: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per leg, the (positions (K, 3), rotations (K, 3, 3), openings (K,)) at the given times
        (s, sorted) that fall into it; times past the end hold the last waypoint."""
        out, t0 = [], 0.0
        pos, rot, opening = self.start
        for k, (p1, r1, o1, seconds) in enumerate(self.legs):
            last = k == len(self.legs) - 1
            mask = (times > t0) & ((times <= t0 + seconds) | last)
            alpha = np.clip((times[mask] - t0) / seconds, 0.0, 1.0) if seconds > 0 else np.ones(mask.sum())
            if mask.any():
                slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([rot, r1])))
                out.append((pos + alpha[:, None] * (p1 - pos), slerp(alpha).as_matrix(),
                            opening + alpha * (o1 - opening)))
            t0, pos, rot, opening = t0 + seconds, p1, r1, o1
        return out


def compose(scene: Scene, start_action: np.ndarray, programs: list[ArmProgram], frame_dt_s: float,
            ik: IKSettings, task: str) -> np.ndarray:
    """Actions (T, 14) from frame 0 = `start_action` on; arms without a program hold their start."""
    duration = max((p.duration for p in programs), default=0.0)
    frames = 1 + int(np.ceil(duration / frame_dt_s - 1e-9))
    times = np.arange(frames) * frame_dt_s
    actions = np.repeat(np.asarray(start_action, np.float32)[None], frames, axis=0)
    for program in programs:
        joints, opening_col = ARM_COLUMNS[program.side]
        q, row = program.start_q, 1
        for leg, (points, rots, openings) in enumerate(program.sample(times)):
            q_leg = solve_poses(scene, program.side, points, rots, q, ik,  # one batch per leg, warm-started
                                f"{task}: the {program.side} arm cannot follow leg {leg}")
            q = q_leg[-1]
            actions[row:row + len(points), joints] = q_leg
            actions[row:row + len(points), opening_col] = openings
            row += len(points)
    return actions


def solve_poses(scene: Scene, side: str, positions: np.ndarray, rotations: np.ndarray, q_init: np.ndarray,
                ik: IKSettings, failure: str) -> np.ndarray:
    """Joint angles (K, 6) putting an arm's TCP at positions (K, 3) with rotations (K, 3, 3), every
    pose warm-started from q_init (6,); InfeasibleEpisode(failure) if any misses the tolerances."""
    q, pos_err, rot_err = solve_tool_ik(
        torch.as_tensor(np.asarray(positions, np.float32)), torch.as_tensor(np.asarray(rotations, np.float32)),
        torch.as_tensor(np.repeat(np.asarray(q_init, np.float32)[None], len(positions), axis=0)),
        torch.as_tensor(arm_base(scene, side)), iterations=ik.iterations)
    if float(pos_err.max()) > ik.tolerance_m or float(rot_err.max()) > ik.tolerance_rad:
        raise InfeasibleEpisode(f"{failure} (IK error {float(pos_err.max()):.4f} m, {float(rot_err.max()):.3f} rad)")
    return q.numpy()


def reach(scene: Scene, side: str, position: np.ndarray, rotation: np.ndarray, ik: IKSettings, task: str,
          q_init: np.ndarray | None = None) -> np.ndarray:
    """Joint angles (6,) putting an arm's TCP at (position, rotation), from home unless q_init."""
    q0 = scene.home_q if q_init is None else q_init
    return solve_poses(scene, side, np.asarray(position)[None], np.asarray(rotation)[None], q0, ik,
                       f"{task}: the {side} arm cannot reach {np.round(position, 3).tolist()}")[0]
