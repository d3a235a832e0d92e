"""When a baseline stops training: its step count, a wall-time budget, or a validation loss that stopped improving."""

from __future__ import annotations

import copy
import time

import torch


class StopRule:
    """Tracks the wall time and the best validation loss of one training run (0 disables either rule).

    `record` after every validation; `converged` once `patience_evals` validations in a row failed to improve on
    the best; `restore_best` loads the best validation weights back (only where the patience rule is on or
    `keep_best` is set, so a run with neither keeps its last weights as before).
    """

    def __init__(self, max_minutes: float = 0.0, patience_evals: int = 0, keep_best: bool = False) -> None:
        self.max_minutes, self.patience_evals, self.keep_best = max_minutes, patience_evals, keep_best
        self.started = time.monotonic()
        self.best_val = float("inf")
        self.best_step = 0
        self.best_state: dict[str, torch.Tensor] | None = None
        self.since_best = 0

    def elapsed_s(self) -> float:
        return time.monotonic() - self.started

    def out_of_time(self) -> bool:
        return self.max_minutes > 0 and self.elapsed_s() > 60.0 * self.max_minutes

    def record(self, step: int, val_loss: float, model: torch.nn.Module) -> None:
        if val_loss < self.best_val:
            self.best_val, self.best_step, self.since_best = val_loss, step, 0
            if self.patience_evals or self.keep_best:
                self.best_state = copy.deepcopy(model.state_dict())
        else:
            self.since_best += 1

    def converged(self) -> bool:
        return self.patience_evals > 0 and self.since_best >= self.patience_evals

    def restore_best(self, model: torch.nn.Module) -> None:
        if self.best_state is not None:
            model.load_state_dict(self.best_state)

    def reason(self, steps_done: int, steps: int) -> str:
        """Why the run ended: "converged", "time" or "steps"."""
        if self.converged():
            return "converged"
        return "steps" if steps_done >= steps else "time"
