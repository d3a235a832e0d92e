"""Which checkpoint ships: the score each evaluation gets (`train.select_by`).

`val_loss`: the segment loss of W-frame validation windows (short horizons; the default).
`rollout`: the position MSE of autoregressive rollouts of whole held-out episodes (`train.rollout_frames` steps
from each val-split episode phase), and no checkpoint whose rollouts diverge - a non-finite state or a rest edge
stretched beyond `train.select_max_strain` at any frame - is ever chosen: a model that wins on short windows but
tears the cloth over a long horizon is what long-horizon generation must not get.
"""

from __future__ import annotations

import math
from typing import Any

import torch

SELECT_BY = ("val_loss", "rollout")


def max_edge_strain(x: torch.Tensor, edges: torch.Tensor, rest_lengths: torch.Tensor) -> float:
    """Largest (length / rest length - 1) of any rest edge over every frame of x (..., N, 3); inf if not finite."""
    if edges.numel() == 0:
        return 0.0 if bool(torch.isfinite(x).all()) else math.inf
    length = (x[..., edges[:, 1], :] - x[..., edges[:, 0], :]).norm(dim=-1)
    strain = length / rest_lengths.clamp_min(1e-12) - 1.0
    return float(strain.max()) if bool(torch.isfinite(strain).all()) else math.inf


def selection_score(losses: dict[str, Any], select_by: str) -> float:
    """Lower is better; inf for a checkpoint that must not ship."""
    if select_by == "val_loss":
        return float(losses["val_loss"])
    if select_by != "rollout":
        raise ValueError(f"train.select_by must be one of {SELECT_BY}, got {select_by!r}")
    mse = float(losses.get("rollout_position_mse_m2", math.nan))
    if losses.get("rollout_diverged", 1) > 0 or not math.isfinite(mse):
        return math.inf
    return mse
