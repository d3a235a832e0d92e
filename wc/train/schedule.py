"""Learning rate at an optimisation step: linear warm-up, then cosine decay (paper Appendix)."""

from __future__ import annotations

import math

from wc.train.config import Schedule


def learning_rate(schedule: Schedule, step: int) -> float:
    """lr at `step` (0-based) of a stage: start → peak over warmup_steps, cosine peak → final by `steps`."""
    if step < schedule.warmup_steps:
        return schedule.start_lr + (schedule.peak_lr - schedule.start_lr) * step / schedule.warmup_steps
    decay = max(1, schedule.steps - schedule.warmup_steps)
    progress = min(1.0, (step - schedule.warmup_steps) / decay)
    return schedule.final_lr + 0.5 * (schedule.peak_lr - schedule.final_lr) * (1.0 + math.cos(math.pi * progress))
