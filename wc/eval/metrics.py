"""Rollout errors: vertex position and velocity MSE, pooled over vertices and frames, per task and per step.

MSE here is the paper's: the mean over vertices (all predicted objects) and frames of the squared
Euclidean error, ‖x̂ − x‖² in m² and ‖v̂ − v‖² in m²/s². Rollouts of different length and vertex count
pool by vertex-frames; step k of every rollout that reaches it pools into the horizon curve.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def squared_error(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(T,) mean over vertices of ‖pred − true‖² per frame; pred, true (T, N, 3). NaN where pred is non-finite."""
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    if pred.shape != true.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"pred and true must both be (T, N, 3), got {pred.shape} and {true.shape}")
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.square(pred - true).sum(axis=-1).mean(axis=1)
    return np.where(np.isfinite(err), err, np.nan)


def finite_or_none(value: float) -> float | None:
    """JSON-safe float: None for NaN / Inf (a diverged method)."""
    return float(value) if value is not None and math.isfinite(value) else None


@dataclass
class _Sums:
    """Per-step sums of vertex-weighted squared errors and vertex counts."""

    x: np.ndarray
    v: np.ndarray
    count: np.ndarray

    @classmethod
    def zeros(cls, horizon: int) -> _Sums:
        return cls(np.zeros(horizon), np.zeros(horizon), np.zeros(horizon))


@dataclass
class ErrorTally:
    """Accumulates rollout errors of one method; `summary()` gives the overall, per-task and per-step MSEs."""

    horizon: int  # longest rollout, in steps
    tasks: dict[str, _Sums] = field(default_factory=dict)
    rollouts: int = 0
    non_finite_rollouts: int = 0

    def add(self, task: str, x_pred: np.ndarray, v_pred: np.ndarray, x_true: np.ndarray, v_true: np.ndarray) -> None:
        """One rollout: predicted and true x, v (S, N, 3) for steps 1..S (S <= horizon)."""
        ex, ev = squared_error(x_pred, x_true), squared_error(v_pred, v_true)
        steps, n = len(ex), np.asarray(x_true).shape[1]
        if steps > self.horizon:
            raise ValueError(f"rollout of {steps} steps exceeds the tally's horizon {self.horizon}")
        sums = self.tasks.setdefault(task, _Sums.zeros(self.horizon))
        sums.x[:steps] += ex * n  # NaN propagates: a diverged rollout makes its task's MSE undefined
        sums.v[:steps] += ev * n
        sums.count[:steps] += n
        self.rollouts += 1
        self.non_finite_rollouts += int(not (np.isfinite(ex).all() and np.isfinite(ev).all()))

    def _total(self, sums: list[_Sums]) -> _Sums:
        out = _Sums.zeros(self.horizon)
        for s in sums:
            out.x += s.x
            out.v += s.v
            out.count += s.count
        return out

    @staticmethod
    def _mse(s: _Sums) -> dict[str, float | None]:
        n = s.count.sum()
        return {"position_mse_m2": finite_or_none(s.x.sum() / n) if n else None,
                "velocity_mse_m2_s2": finite_or_none(s.v.sum() / n) if n else None}

    def summary(self) -> dict[str, Any]:
        """{position_mse_m2, velocity_mse_m2_s2, per_task: {task: {...}}, per_horizon: {metric: {step: value}}}
        (steps zero-padded, "01".."25"; None where undefined or non-finite)."""
        total = self._total(list(self.tasks.values()))
        reached = total.count > 0
        width = len(str(self.horizon))  # zero-padded step keys sort in step order
        per_step = {
            name: {f"{k + 1:0{width}d}": finite_or_none(s[k] / total.count[k]) for k in np.flatnonzero(reached)}
            for name, s in (("position_mse_m2", total.x), ("velocity_mse_m2_s2", total.v))
        }
        return {**self._mse(total), "per_task": {t: self._mse(s) for t, s in sorted(self.tasks.items())},
                "per_horizon": per_step, "rollouts": self.rollouts, "non_finite_rollouts": self.non_finite_rollouts}
