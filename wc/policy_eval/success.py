"""The lift success predicate: the bag's lowest vertex stays `lift_height_m` above the table top for
`hold_s` without a break (a streak of lifted frames spanning hold_s); and the confidence interval of a success rate."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np


def hold_frames(hold_s: float, frame_dt_s: float) -> int:
    """Frame intervals a lift must last: ceil(hold_s / dt) (0 = lifted once is enough)."""
    return max(0, math.ceil(hold_s / frame_dt_s - 1e-9))


class LiftHoldMonitor:
    """Fed the lowest bag height above the table [m] once per frame; `update` returns True from the frame at
    which the bag has been lifted continuously for `hold` frame intervals."""

    def __init__(self, lift_height_m: float, hold: int) -> None:
        self.lift_height_m, self.hold = lift_height_m, hold
        self.streak = 0  # consecutive lifted frames, this one included
        self.max_height_m = -math.inf
        self.ever_lifted = False

    def update(self, height_m: float) -> bool:
        if not math.isfinite(height_m):
            raise ValueError(f"lowest bag height is not finite ({height_m})")
        self.max_height_m = max(self.max_height_m, height_m)
        lifted = height_m >= self.lift_height_m
        self.streak = self.streak + 1 if lifted else 0
        self.ever_lifted |= lifted
        return self.streak > self.hold  # streak of n frames spans n - 1 intervals

    def failure(self) -> str:
        """Why an episode that ended without success failed: not_lifted (never lifted), dropped (lifted, then
        fell back below the height) or not_held (still lifted, for too short a time)."""
        return "not_lifted" if not self.ever_lifted else "not_held" if self.streak else "dropped"


class TrialJudge:
    """One closed-loop trial's verdict, fed once per frame: success (the lift held), terminated by a non-finite
    action or state, or truncated (failed as the monitor says) at the first frame from which the hold can no longer
    complete by `max_steps`: the verdict it would get at max_steps, without stepping a lost trial on. Once the trial
    has ended its verdict is final: both the per-trial env and the batched one (whose ended worlds keep stepping)
    judge with this."""

    def __init__(self, lift_height_m: float, hold: int, max_steps: int) -> None:
        self.monitor = LiftHoldMonitor(lift_height_m, hold)
        self.max_steps = max_steps
        self.steps = 0
        self.success = False
        self.failure: str | None = None  # None while running and on success
        self.done = False

    def start(self, height_m: float) -> bool:
        """Frame 0 (the bag rests on the table there); True if it already satisfies the predicate."""
        return self.monitor.update(height_m)

    def step(self, height_m: float, failure: str | None = None) -> tuple[bool, bool, bool]:
        """One more frame: its lowest bag height [m], or the failure that ended it (non_finite_action | non_finite).
        Returns (success, terminated, truncated)."""
        if self.done:
            raise RuntimeError("the trial has ended: its verdict is final")
        self.steps += 1
        self.failure = failure
        self.success = failure is None and self.monitor.update(height_m)
        terminated = self.success or failure is not None
        reachable = self.monitor.streak + (self.max_steps - self.steps)  # longest streak possible at max_steps
        truncated = not terminated and reachable <= self.monitor.hold  # always so at max_steps without success
        if truncated:
            self.failure = self.monitor.failure()
        self.done = terminated or truncated
        return self.success, terminated, truncated


def first_success(heights_m: Iterable[float], lift_height_m: float, hold: int) -> int | None:
    """Index of the first frame at which the heights sequence (m, one per frame) satisfies the predicate."""
    monitor = LiftHoldMonitor(lift_height_m, hold)
    for k, h in enumerate(np.asarray(list(heights_m), np.float64)):
        if monitor.update(float(h)):
            return k
    return None


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a success rate (z = 1.96: 95 %); unlike the normal approximation it stays inside
    [0, 1] and is not empty at 0 or `trials` successes."""
    if trials < 1 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials >= 1, got {successes} / {trials}")
    p, n = successes / trials, trials
    denominator = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)
