"""The recorded frames before a rollout's frame 0, for predictors that read past frames (the particle baselines)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class PastFrames:
    """The K recorded frames before a rollout's frame 0, oldest first (K >= 0)."""

    x: torch.Tensor  # (B, K, N, 3) vertex positions, m
    v: torch.Tensor  # (B, K, N, 3) vertex velocities, m/s
    poses: torch.Tensor  # (B, K, P, 7) body poses of the layout's bodies

    def __post_init__(self) -> None:
        x, v, poses = self.x.shape, self.v.shape, self.poses.shape
        if len(x) != 4 or v != x or len(poses) != 4 or poses[:2] != x[:2]:
            raise ValueError(f"past frames need x, v (B, K, N, 3) and poses (B, K, P, 7), got x {tuple(x)}, v {tuple(v)}, "
                             f"poses {tuple(poses)}")
