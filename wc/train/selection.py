"""Which checkpoint ships: the score each evaluation gets (`train.select_by`).

`val_loss`: the segment loss of W-frame validation windows (short horizons; the default).
`rollout`: the position MSE of autoregressive rollouts of whole held-out episodes (`train.rollout_frames` steps
from each val-split episode phase), and no checkpoint whose rollouts diverge - a non-finite state or a rest edge
stretched beyond `train.select_max_strain` at any frame - is ever chosen: a model that wins on short windows but
tears the cloth over a long horizon is what long-horizon generation must not get.

Which stage ships (`train.ship_stage`): `best`, the stage whose best checkpoint scores lower; `last`, the last stage
that ran (projection, when it has steps). The projection's corrections count against it on windows, so `best` can ship
a base-stage model without the topology projection even after fine-tuning a projection-stage one
(reports/gpu/gpu_policy_run_h200.md: edge strain 0.80 against 0.15, a third of the generated lifts blew up).
"""

from __future__ import annotations

import math
from typing import Any

import torch

SELECT_BY = ("val_loss", "rollout")
SHIP_STAGES = ("best", "last")


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


def shipped_stage(best: dict[str, float], ship_stage: str) -> str:
    """The stage whose best checkpoint ships, from each stage's best score (stages in training order)."""
    if ship_stage not in SHIP_STAGES:
        raise ValueError(f"train.ship_stage must be one of {SHIP_STAGES}, got {ship_stage!r}")
    if not best:
        raise ValueError("no stage saved a checkpoint")
    return list(best)[-1] if ship_stage == "last" else min(best, key=lambda stage: best[stage])
