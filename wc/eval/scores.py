"""One method's held-out scores: errors and penetration over every rollout (overall, per task), per motion phase of
the phase-start rollouts, and over the whole-span rollouts (per task: what the whole-episode ratios compare), and its
rollout time (wc.eval.rollout_plan says which rollouts there are)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from wc.eval.cases import Case
from wc.eval.metrics import ErrorTally, finite_or_none
from wc.eval.penetration import PenetrationTally
from wc.eval.rollout_plan import EPISODE


@dataclass
class MethodScores:
    """Tallies of one method; `rollout_frames`, `episode_frames`: the longest phase-start and whole rollouts (steps)."""

    rollout_frames: int
    episode_frames: int
    depth_m: float
    band_m: float
    seconds: float = 0.0
    steps: int = 0
    task_penetration: dict[str, PenetrationTally] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.errors = ErrorTally(max(self.rollout_frames, self.episode_frames))
        self.phase_errors = ErrorTally(self.rollout_frames)  # keyed by the motion phase of the start frame
        self.episode_errors = ErrorTally(self.episode_frames)  # keyed by task
        self.penetration = PenetrationTally(self.depth_m, self.band_m)
        self.episode_penetration = PenetrationTally(self.depth_m, self.band_m)

    def add(self, case: Case, x: np.ndarray, v: np.ndarray, signed_distance: np.ndarray, label: str) -> None:
        """One rollout's predicted x, v (S, N, 3) and cloth signed distances (S, N_cloth); `label` EPISODE for a
        whole-span rollout, else the motion phase of its start frame."""
        truth = (case.x[1:], case.v[1:])
        self.errors.add(case.task, x, v, *truth)
        self.penetration.add(signed_distance, case.cloth_area)
        task = self.task_penetration.setdefault(case.task, PenetrationTally(self.depth_m, self.band_m))
        task.add(signed_distance, case.cloth_area)
        if label == EPISODE:
            self.episode_errors.add(case.task, x, v, *truth)
            self.episode_penetration.add(signed_distance, case.cloth_area)
        else:
            self.phase_errors.add(label, x, v, *truth)

    @staticmethod
    def _rates(tally: PenetrationTally) -> dict[str, float | None]:
        return {"penetration_rate_pct": finite_or_none(tally.rate_pct),
                "contact_penetration_rate_pct": finite_or_none(tally.contact_rate_pct)}

    def summary(self) -> dict[str, Any]:
        """The errors summary (wc.eval.metrics.ErrorTally) of every rollout with penetration rates, `per_phase`
        {phase: MSEs}, `whole_episode` {MSEs, per_task, rollouts, penetration rates} and s_per_step."""
        out = {**self.errors.summary(), **self._rates(self.penetration)}
        for task, tally in self.task_penetration.items():
            out["per_task"][task].update(self._rates(tally))
        out["per_phase"] = self.phase_errors.summary()["per_task"]
        whole = self.episode_errors.summary()
        out["whole_episode"] = {**{k: whole[k] for k in ("position_mse_m2", "velocity_mse_m2_s2", "per_task",
                                                          "rollouts", "non_finite_rollouts")},
                                **self._rates(self.episode_penetration)}
        out["s_per_step"] = finite_or_none(self.seconds / self.steps) if self.steps else None
        return out
