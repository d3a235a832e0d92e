"""Cloth held between closed finger pads is carried with them (an option of the expand stage's projection).

A learnt step may let a pinched strap slip out of closed pads that Newton's friction holds. Here a cloth vertex
within `radius_m` of both pad boxes of one arm at frame t (only closed pads are that close to one point) is held:
at t + 1 it moves rigidly with the pads, by the mean of the two fingers' motions from t to t + 1, with the velocity
of that motion, and the constraint projection keeps it pinned (`ConstraintProjection.project(pinned=...)`).
Nothing is bag-specific: every cloth object of the scene, both arms' pads.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from wc.scene.scene import Scene
from wc.rotations import quat_conjugate, quat_rotate
from wc.validate.predicates import OPENING_COLUMNS, box_signed_distance, cloth_rows, finger_pad_boxes

def held_between_pads(scene: Scene, x: np.ndarray, link_poses: np.ndarray, radius_m: float) -> np.ndarray:
    """(B, n) bool: cloth points x (B, n, 3) within radius_m of both pad boxes of one arm posed by link_poses
    (B, L, 7)."""
    held = np.zeros(x.shape[:2], bool)
    for side in OPENING_COLUMNS:
        centre, quat, half = finger_pad_boxes(scene, link_poses, side)  # (B, 2, 3), (B, 2, 4), (2, 3)
        near = [box_signed_distance(x, centre[:, k, None], quat[:, k, None], half[k]) <= radius_m for k in (0, 1)]
        held |= near[0] & near[1]
    return held


def finger_motion(scene: Scene, x: np.ndarray, before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Points x (B, n, 3) moved by the mean of the two fingers' rigid motions (either arm: the nearer pads') from
    link poses `before` to `after` (B, L, 7)."""
    moved = np.empty_like(x)
    best = np.full(x.shape[:2], np.inf)
    for side in OPENING_COLUMNS:
        cols = [scene.link_names.index(f"{side}_{f}") for f in ("finger_a", "finger_b")]
        p0, p1 = before[:, cols].astype(np.float64), after[:, cols].astype(np.float64)  # (B, 2, 7)
        local = quat_rotate(quat_conjugate(p0[:, :, None, 3:]), x[:, None] - p0[:, :, None, :3])  # (B, 2, n, 3)
        world = (quat_rotate(p1[:, :, None, 3:], local) + p1[:, :, None, :3]).mean(axis=1)
        dist = np.linalg.norm(x[:, None] - p0[:, :, None, :3], axis=-1).min(axis=1)  # (B, n)
        closer = dist < best
        moved[closer], best[closer] = world[closer], dist[closer]
    return moved


class PadCarry:
    """Held cloth vertices follow the pads for one step (module docstring)."""

    def __init__(self, scene: Scene, radius_m: float) -> None:
        if not radius_m > 0:
            raise ValueError(f"pad carry radius must be positive, got {radius_m}")
        self.scene, self.radius_m = scene, float(radius_m)
        self.rows = cloth_rows(scene)

    @torch.no_grad()
    def apply(self, x_prev: Tensor, x: Tensor, v: Tensor, dt: float, before: np.ndarray, after: np.ndarray
              ) -> tuple[Tensor, Tensor, Tensor]:
        """(x, v, pinned (B, N) bool) of a predicted step x, v (B, N, 3) from x_prev, with the vertices held at
        link poses `before` (B, L, 7) carried to `after`."""
        pinned = torch.zeros(x.shape[:2], dtype=torch.bool, device=x.device)
        if len(self.rows) == 0:
            return x, v, pinned
        prev = np.nan_to_num(x_prev[:, self.rows].detach().double().cpu().numpy())
        held = held_between_pads(self.scene, prev, before, self.radius_m)
        if not held.any():
            return x, v, pinned
        carried = torch.as_tensor(finger_motion(self.scene, prev, before, after), dtype=x.dtype, device=x.device)
        rows = torch.as_tensor(self.rows, device=x.device)
        mask = torch.as_tensor(held, device=x.device)[..., None]
        x_out, v_out = x.clone(), v.clone()
        x_out[:, rows] = torch.where(mask, carried, x[:, rows])
        v_out[:, rows] = torch.where(mask, (carried - x_prev[:, rows]) / dt, v[:, rows])
        pinned[:, rows] = mask[..., 0]
        return x_out, v_out, pinned
