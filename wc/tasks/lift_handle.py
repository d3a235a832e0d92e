"""Task 8, the policy task "right grasp and lift": pinch one handle with the right gripper, lift, hold.

Coverage cell = (grasp depth below the handle's apex, position across the strap, initial bag yaw);
speed = TCP speed [m/s]; amplitude = lift height [m].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from wc.dynamics import ObjectState
from wc.scene.ik import solve_tool_ik
from wc.scene.piper import tool_pose
from wc.scene.scene import Scene
from wc.sim.kinematic import quat_rotate
from wc.tasks.base import EpisodeSpec, InfeasibleEpisode, register_task


@dataclass(frozen=True)
class LiftHandleConfig:
    grasp_depth_bins_m: tuple[float, ...]  # pinch this far below the handle apex
    grasp_across_bins: tuple[float, ...]  # position across the strap width, 0..1
    yaw_bins_deg: tuple[float, ...]  # initial bag yaw about z
    bag_center_xy_m: tuple[float, float]
    bag_jitter_m: float  # uniform xy jitter of the initial bag position
    drop_height_m: float  # bag bottom above the table top before settling
    speed_range_m_s: tuple[float, float]  # TCP speed
    amplitude_range_m: tuple[float, float]  # lift height
    start_height_m: float  # TCP distance back along the approach axis while the bag settles
    approach_height_m: float  # pre-grasp TCP distance back along the approach axis
    approach_tilt_deg: float  # approach axis tilted from vertical, away from the arm's base
    lift_tilt_deg: float  # tilt at the top of the lift (the arm reaches higher with more tilt)
    lift_retract_m: float  # the lift also pulls back this far towards the arm's base
    open_m: float  # gripper opening while approaching
    closed_m: float  # commanded opening when pinching
    close_s: float
    hold_s: float
    ik_iterations: int
    ik_tolerance_m: float  # a plan whose IK misses by more is infeasible (a jerky arm would shake the grip)
    ik_tolerance_rad: float
    success_lift_m: float  # accepted if the bag's lowest vertex ends this far above the table

    def validate(self) -> None:
        for name in ("grasp_depth_bins_m", "grasp_across_bins", "yaw_bins_deg"):
            if not getattr(self, name):
                raise ValueError(f"{name} must list at least one bin")
        lo, hi = self.speed_range_m_s
        if not 0 < lo <= hi:
            raise ValueError(f"speed_range_m_s must satisfy 0 < low <= high, got {self.speed_range_m_s}")
        lo, hi = self.amplitude_range_m
        if not 0 < lo <= hi:
            raise ValueError(f"amplitude_range_m must satisfy 0 < low <= high, got {self.amplitude_range_m}")
        if self.close_s <= 0 or self.hold_s < 0:
            raise ValueError("close_s must be positive and hold_s non-negative")


def _handle_of_right_arm(scene: Scene, x: np.ndarray) -> str:
    """The bag handle nearer the right arm's base."""
    bag = scene.objects["bag"]
    centroid = {g: x[bag.groups[g]].mean(0) for g in ("handle_0", "handle_1")}
    return min(centroid, key=lambda g: np.linalg.norm(centroid[g][:2] - scene.right_base[:2]))


def tool_rotation(separation: np.ndarray, away: np.ndarray, tilt_deg: float) -> np.ndarray:
    """TCP rotation (3, 3) [x, y = pad separation, z = approach]: the approach points down, tilted by
    tilt_deg towards the horizontal `away`; the pads separate along `separation` made normal to it."""
    tilt = np.deg2rad(tilt_deg)
    z = -np.cos(tilt) * np.array([0.0, 0.0, 1.0]) + np.sin(tilt) * away
    y = separation - (separation @ z) * z
    y /= np.linalg.norm(y)
    return np.stack([np.cross(y, z), y, z], axis=1)


def grasp_frame(scene: Scene, x: np.ndarray, depth_m: float, across: float,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grasp point (3,), pad separation axis (3,) and horizontal direction away from the right arm's
    base (3,) for pinching the right-arm handle in state x.

    The pads straddle the strap's two legs below its apex and squeeze them together: the pad
    separation axis is the strap's horizontal front-to-back direction; the approach points down,
    tilted away from the arm's base (a PiPER cannot point straight down at handle height).
    """
    bag = scene.objects["bag"]
    xb = x[scene.vertex_slices()["bag"]]
    idx = bag.groups[_handle_of_right_arm(scene, xb)]
    u, s = bag.attributes["handle_u"][idx], bag.attributes["handle_s"][idx]
    band = idx[np.abs(u - across) <= np.abs(u - across).min() + 1e-6]
    apex = xb[band[np.argmax(xb[band, 2])]]
    point = apex - np.array([0.0, 0.0, depth_m])
    sep = xb[idx[s < 0.5]].mean(0) - xb[idx[s > 0.5]].mean(0)
    sep[2] = 0.0
    y = sep / np.linalg.norm(sep) if np.linalg.norm(sep) > 1e-6 else np.array([0.0, 1.0, 0.0])
    home_y = quat_rotate(scene.right_base[3:], np.array([0.0, 1.0, 0.0]))  # TCP y at home, yawed with the base
    y = y if y @ home_y >= 0 else -y  # the pads are symmetric: take the sign that needs the least wrist roll
    # centre the pads between the strap's legs at and below the pinch height (a settled strap may lean)
    legs = xb[idx[(xb[idx, 2] <= point[2] + 0.5 * depth_m) & (xb[idx, 2] >= point[2] - depth_m)]]
    if len(legs):
        spread = (legs - point) @ y
        point = point + 0.5 * (spread.min() + spread.max()) * y
    away = point - scene.right_base[:3]  # radial: the arm tilts its tool most easily in its own plane
    away[2] = 0.0
    away = away / np.linalg.norm(away) if np.linalg.norm(away) > 1e-6 else np.zeros(3)
    return point, y, away


@register_task("lift_handle", LiftHandleConfig)
class LiftHandle:
    objects = ("bag",)

    def __init__(self, config: LiftHandleConfig):
        self.cfg = config

    def _cell(self, cell: int) -> tuple[float, float, float]:
        shape = (len(self.cfg.grasp_depth_bins_m), len(self.cfg.grasp_across_bins), len(self.cfg.yaw_bins_deg))
        i, j, k = np.unravel_index(cell % self.num_cells(), shape)
        return self.cfg.grasp_depth_bins_m[i], self.cfg.grasp_across_bins[j], self.cfg.yaw_bins_deg[k]

    def num_cells(self) -> int:
        return len(self.cfg.grasp_depth_bins_m) * len(self.cfg.grasp_across_bins) * len(self.cfg.yaw_bins_deg)

    def speed_range(self) -> tuple[float, float]:
        return self.cfg.speed_range_m_s

    def amplitude_range(self) -> tuple[float, float]:
        return self.cfg.amplitude_range_m

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        _, _, yaw = self._cell(spec.cell)
        half = np.deg2rad(yaw) / 2.0
        quat = np.array([0.0, 0.0, np.sin(half), np.cos(half)])
        centre = np.asarray(self.cfg.bag_center_xy_m) + rng.uniform(-1, 1, 2) * self.cfg.bag_jitter_m
        offset = np.array([*centre, scene.table.top_z + self.cfg.drop_height_m])
        x = quat_rotate(quat[None], scene.objects["bag"].vertices) + offset
        return ObjectState(x.astype(np.float32), np.zeros_like(x, dtype=np.float32))

    def _solve(self, scene: Scene, points: np.ndarray, rot: np.ndarray, q_init: np.ndarray) -> np.ndarray:
        """Right-arm joints (K, 6) reaching TCP points (K, 3) with rotations (3, 3) or (K, 3, 3), warm-started."""
        q, pos_err, rot_err = solve_tool_ik(
            torch.as_tensor(points, dtype=torch.float32),
            torch.as_tensor(np.broadcast_to(rot, (len(points), 3, 3)).copy(), dtype=torch.float32),
            torch.as_tensor(q_init, dtype=torch.float32), torch.as_tensor(scene.right_base),
            iterations=self.cfg.ik_iterations)
        if float(pos_err.max()) > self.cfg.ik_tolerance_m or float(rot_err.max()) > self.cfg.ik_tolerance_rad:
            raise InfeasibleEpisode(f"lift_handle: target out of the right arm's reach (IK error "
                                    f"{float(pos_err.max()):.4f} m, {float(rot_err.max()):.3f} rad)")
        return q.numpy()

    def _start_q(self, scene: Scene, x: np.ndarray, spec: EpisodeSpec) -> np.ndarray:
        depth, across, _ = self._cell(spec.cell)
        point, y, away = grasp_frame(scene, x, depth, across)
        rot = tool_rotation(y, away, self.cfg.approach_tilt_deg)
        above = point - self.cfg.start_height_m * rot[:, 2]
        return self._solve(scene, above[None], rot, np.asarray(scene.home_q, np.float32)[None])[0]

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        action = scene.home_action()
        action[7:13] = self._start_q(scene, initial.x, spec)
        action[13] = self.cfg.open_m
        return action

    def check(self, scene: Scene, x: np.ndarray, action: np.ndarray) -> str | None:
        """'not_lifted' unless the bag's lowest vertex is success_lift_m above the table at the end."""
        bag = x[-1, scene.vertex_slices()["bag"]]
        return None if bag[:, 2].min() - scene.table.top_z >= self.cfg.success_lift_m else "not_lifted"

    def actions(self, scene: Scene, settled: ObjectState, spec: EpisodeSpec, start: np.ndarray,
                frame_dt_s: float) -> np.ndarray:
        cfg = self.cfg
        depth, across, _ = self._cell(spec.cell)
        grasp, y, away = grasp_frame(scene, settled.x, depth, across)
        approach = tool_rotation(y, away, cfg.approach_tilt_deg)[:, 2]
        # where the tool really is at frame 0 (planned before the bag settled), so frame 1 does not jump
        start_tcp = tool_pose(torch.as_tensor(start[7:13]), float(start[13]), torch.as_tensor(scene.right_base))
        start_tcp = start_tcp[:3].numpy().astype(np.float64)
        pre = grasp - cfg.approach_height_m * approach
        lifted = grasp + np.array([0.0, 0.0, spec.amplitude]) - cfg.lift_retract_m * away
        tilt0, tilt1 = cfg.approach_tilt_deg, cfg.lift_tilt_deg
        # (TCP position, tilt, gripper opening, duration [s] to reach them from the previous waypoint)
        legs = [(pre, tilt0, cfg.open_m, np.linalg.norm(pre - start_tcp) / spec.speed),
                (grasp, tilt0, cfg.open_m, cfg.approach_height_m / spec.speed),
                (grasp, tilt0, cfg.closed_m, cfg.close_s),
                (lifted, tilt1, cfg.closed_m, np.linalg.norm(lifted - grasp) / spec.speed),
                (lifted, tilt1, cfg.closed_m, cfg.hold_s)]
        return self._trajectory(scene, start, start_tcp, legs, y, away, frame_dt_s)

    def _trajectory(self, scene: Scene, start: np.ndarray, start_tcp: np.ndarray, legs: list, y: np.ndarray,
                    away: np.ndarray, frame_dt_s: float) -> np.ndarray:
        """Frame-by-frame actions (T, 14) following straight TCP legs, IK solved per frame."""
        frames = [start[None]]
        tcp, tilt, opening, q = start_tcp, self.cfg.approach_tilt_deg, start[13], start[7:13]
        for target, target_tilt, target_open, duration in legs:
            n = max(1, int(np.ceil(duration / frame_dt_s)))
            alpha = (np.arange(1, n + 1) / n)[:, None]
            points = (1 - alpha) * tcp + alpha * target
            rots = np.stack([tool_rotation(y, away, (1 - a) * tilt + a * target_tilt) for a in alpha[:, 0]])
            q_leg = self._solve(scene, points, rots, np.repeat(q[None], n, axis=0))
            leg = np.repeat(start[None], n, axis=0)
            leg[:, 7:13] = q_leg
            leg[:, 13] = (1 - alpha[:, 0]) * opening + alpha[:, 0] * target_open
            frames.append(leg)
            tcp, tilt, opening, q = target, target_tilt, target_open, q_leg[-1]
        return np.concatenate(frames).astype(np.float32)
