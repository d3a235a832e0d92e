"""Which episode to run next: a coverage cell, a speed and an amplitude per task.

The agent only calls `Planner.propose`, so another planner can replace this one.
"""

from __future__ import annotations

from collections import Counter
from typing import Protocol

import numpy as np

from wc.tasks.base import EpisodeSpec, Task


class Planner(Protocol):
    def propose(self, task: Task, seed: int) -> EpisodeSpec: ...

    def record(self, spec: EpisodeSpec, failure: str | None) -> None: ...


class CoveragePlanner:
    """Visits the least-visited cell first (ties: lowest index); speed and amplitude drawn uniformly."""

    def __init__(self) -> None:
        self.visits: Counter[tuple[str, int]] = Counter()
        self.accepted: Counter[tuple[str, int]] = Counter()

    def propose(self, task: Task, seed: int) -> EpisodeSpec:
        rng = np.random.default_rng(seed)
        cell = min(range(task.num_cells()), key=lambda c: (self.visits[(task.name, c)], c))
        self.visits[(task.name, cell)] += 1
        speed = float(rng.uniform(*task.speed_range()))
        amplitude = float(rng.uniform(*task.amplitude_range()))
        return EpisodeSpec(task.name, seed, cell, speed, amplitude)

    def record(self, spec: EpisodeSpec, failure: str | None) -> None:
        if failure is None:
            self.accepted[(spec.task, spec.cell)] += 1

    def coverage(self, task: Task) -> dict[str, int]:
        cells = range(task.num_cells())
        return {"cells": task.num_cells(),
                "cells_visited": sum(self.visits[(task.name, c)] > 0 for c in cells),
                "cells_accepted": sum(self.accepted[(task.name, c)] > 0 for c in cells)}
