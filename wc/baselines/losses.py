"""Set losses on particle clouds: exact EMD (Hungarian assignment, scipy) and Chamfer distance (torch).

Both use Euclidean (not squared) distances, as RoboCraft and RoboCook do, and average over the
leading batch dimensions.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment


def _check(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape or pred.ndim < 2 or pred.shape[-1] != 3:
        raise ValueError(f"pred and target must both be (..., K, 3), got {tuple(pred.shape)} and {tuple(target.shape)}")


def emd(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Earth mover's distance (m) between equal-size clouds (..., K, 3): mean matched distance of the optimal
    one-to-one assignment (exact, scipy's linear_sum_assignment; the gradient flows through the matched pairs)."""
    _check(pred, target)
    p, q = pred.reshape(-1, *pred.shape[-2:]), target.reshape(-1, *target.shape[-2:])
    cost = torch.cdist(p.detach().double(), q.detach().double()).cpu().numpy()
    match = np.stack([linear_sum_assignment(c)[1] for c in cost])  # (batch, K): target index per pred point
    index = torch.from_numpy(match).to(pred.device)
    matched = torch.gather(q, 1, index[..., None].expand(-1, -1, 3))
    return (p - matched).norm(dim=-1).mean()


def chamfer(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Chamfer distance (m) between clouds (..., K, 3): mean nearest distance pred -> target plus target -> pred."""
    _check(pred, target)
    d = torch.cdist(pred.reshape(-1, *pred.shape[-2:]), target.reshape(-1, *target.shape[-2:]))
    return d.min(dim=2).values.mean() + d.min(dim=1).values.mean()
