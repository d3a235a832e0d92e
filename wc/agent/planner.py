"""Which episode to run next: a coverage cell, a speed and an amplitude per task.

The agent only calls the three methods of `Planner`, so another planner can replace this one.

`CoveragePlanner`'s rules, all deterministic given the episode seed and the memory:

- Cell: the one with the fewest accepted episodes (memory, which includes this run), ties by
  fewest episodes run or in flight, then lowest index. Episodes proposed but not yet recorded
  count as accepted (optimistically), so a batch proposed before any verdict spreads over the
  cells. A cell whose last `give_up_after` outcomes are all failures comes after every cell that is not.
- Range, per cell, recomputed from all of that cell's outcomes. While the cell has no success,
  every failure is charged to both dimensions (speed and amplitude); after that, each failure is
  charged only to the dimension in which it lies farthest outside the successes, as a fraction of
  the task's range (ties: speed). Then, per dimension, failures charged to it that lie above
  every success (all of them, if the cell has no success yet) lower the high end to the midpoint
  between the highest success (the range's low end, if none) and the lowest such failure; those
  below every success raise the low end to the midpoint between the highest such failure and the
  lowest success. Failures between successes leave the range alone. So each range bisects
  towards the boundary between succeeding and failing values, and once a success is seen a
  failure caused by speed no longer narrows the amplitudes.
- Sample: uniform in the shrunk ranges; a draw within `same_sample_tol` (a fraction of the width of
  the task's range) of an earlier failure of the cell in both speed and amplitude is redrawn, from
  the task's full ranges once the shrunk ones have yielded nothing new.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from typing import Protocol

import numpy as np

from wc.agent.memory import FailureMemory, Outcome
from wc.tasks.base import EpisodeSpec, Task

_DRAWS = 16  # redraws per range before widening to the task's full ranges


class Planner(Protocol):
    def propose(self, task: Task, seed: int) -> EpisodeSpec:
        """The next episode of `task`; `seed` is its own, so proposals are reproducible."""
        ...

    def record(self, spec: EpisodeSpec, failure: str | None, frame: int | None = None) -> None:
        """The verdict of a proposed episode: its first failing predicate (and frame), None if accepted."""
        ...

    def coverage(self, task: Task) -> dict[str, int]:
        """Cell counts for the stage report: at least cells, cells_visited and cells_accepted."""
        ...


class CoveragePlanner:
    """Fills under-covered cells first and learns from failures (rules in the module docstring)."""

    def __init__(self, memory: FailureMemory | None = None, task_keys: Mapping[str, str] | None = None,
                 give_up_after: int = 3, same_sample_tol: float = 1e-3) -> None:
        """`memory`: outcomes of earlier runs, appended to by `record` (None: this run only).
        `task_keys`: task name -> a key of its configuration; outcomes under another key are not
        used (None: the task name is the key)."""
        if give_up_after < 1:
            raise ValueError(f"give_up_after must be >= 1, got {give_up_after}")
        if same_sample_tol < 0:
            raise ValueError(f"same_sample_tol must be >= 0, got {same_sample_tol}")
        self.memory = memory if memory is not None else FailureMemory()
        self.task_keys = dict(task_keys) if task_keys is not None else None
        self.give_up_after = give_up_after
        self.same_sample_tol = same_sample_tol
        self.visits: Counter[tuple[str, int]] = Counter()  # proposed this run, by (task, cell)
        self.accepted: Counter[tuple[str, int]] = Counter()  # accepted this run
        self._pending: Counter[tuple[str, int]] = Counter()  # proposed, verdict not yet recorded

    def task_key(self, name: str) -> str:
        """The key task `name`'s outcomes are filed under in the memory."""
        if self.task_keys is None:
            return name
        if name not in self.task_keys:
            raise KeyError(f"no task key for task {name!r}; task_keys has {sorted(self.task_keys)}")
        return self.task_keys[name]

    def propose(self, task: Task, seed: int) -> EpisodeSpec:
        key = self.task_key(task.name)
        cell = min(range(task.num_cells()), key=lambda c: self._priority(task.name, key, c))
        speed, amplitude = self._fresh_sample(np.random.default_rng(seed), self.memory.outcomes(key, cell),
                                              task.speed_range(), task.amplitude_range())
        self.visits[(task.name, cell)] += 1
        self._pending[(task.name, cell)] += 1
        return EpisodeSpec(task.name, seed, cell, speed, amplitude)

    def record(self, spec: EpisodeSpec, failure: str | None, frame: int | None = None) -> None:
        slot = (spec.task, spec.cell)
        if self._pending[slot] > 0:
            self._pending[slot] -= 1
        if failure is None:
            self.accepted[slot] += 1
        self.memory.record(self.task_key(spec.task), spec, failure, frame)  # the caller saves the memory

    def coverage(self, task: Task) -> dict[str, int]:
        """Cells with at least one episode proposed / accepted, this run and over all runs
        (the memory's, this one's included); cells_given_up: cells deprioritised for failing."""
        key = self.task_key(task.name)
        cells = range(task.num_cells())
        visits, accepted = self.memory.visits(key), self.memory.accepted(key)
        return {"cells": task.num_cells(),
                "cells_visited": sum(self.visits[(task.name, c)] > 0 for c in cells),
                "cells_accepted": sum(self.accepted[(task.name, c)] > 0 for c in cells),
                "cells_visited_all_runs": sum(visits[c] + self.visits[(task.name, c)] > 0 for c in cells),
                "cells_accepted_all_runs": sum(accepted[c] > 0 for c in cells),
                "cells_given_up": sum(self._gave_up(self.memory.outcomes(key, c)) for c in cells)}

    def _priority(self, name: str, key: str, cell: int) -> tuple[bool, int, int, int]:
        history = self.memory.outcomes(key, cell)
        pending = self._pending[(name, cell)]
        accepted = sum(o.failure is None for o in history)
        return self._gave_up(history), accepted + pending, len(history) + pending, cell

    def _gave_up(self, history: list[Outcome]) -> bool:
        recent = history[-self.give_up_after:]
        return len(recent) == self.give_up_after and all(o.failure is not None for o in recent)

    def _fresh_sample(self, rng: np.random.Generator, history: list[Outcome], speed_full: tuple[float, float],
                      amplitude_full: tuple[float, float]) -> tuple[float, float]:
        """(speed, amplitude) from the cell's shrunk ranges, unlike any of its failed samples."""
        shrunk = shrunk_ranges((speed_full, amplitude_full), [(o.speed, o.amplitude) for o in history],
                               [o.failure is not None for o in history])
        tol_speed = self.same_sample_tol * (speed_full[1] - speed_full[0])
        tol_amplitude = self.same_sample_tol * (amplitude_full[1] - amplitude_full[0])
        failures = [o for o in history if o.failure is not None]
        for attempt in range(2 * _DRAWS):
            speed_range, amplitude_range = shrunk if attempt < _DRAWS else (speed_full, amplitude_full)
            speed = float(rng.uniform(*speed_range))
            amplitude = float(rng.uniform(*amplitude_range))
            if not any(abs(speed - o.speed) <= tol_speed and abs(amplitude - o.amplitude) <= tol_amplitude
                       for o in failures):
                return speed, amplitude
        return speed, amplitude  # only when the task's ranges are single points that already failed


def shrunk_ranges(full: tuple[tuple[float, float], ...], samples: list[tuple[float, ...]],
                  failed: list[bool]) -> tuple[tuple[float, float], ...]:
    """Each dimension's (low, high) of `full` narrowed away from the failing `samples` (rule in the
    module docstring); `samples[i]` has one value per dimension."""
    ok = [sample for sample, f in zip(samples, failed) if not f]
    charged: list[list[float]] = [[] for _ in full]
    for sample, f in zip(samples, failed):
        if f and not ok:  # nothing to tell the dimensions apart by yet
            for d, v in enumerate(sample):
                charged[d].append(v)
        elif f:
            excess = [_excess(v, [o[d] for o in ok], full[d]) for d, v in enumerate(sample)]
            d = int(np.argmax(excess))  # first maximum: ties go to the earlier dimension
            if excess[d] > 0:
                charged[d].append(sample[d])
    return tuple(shrunk_range(full[d], [o[d] for o in ok], charged[d]) for d in range(len(full)))


def shrunk_range(full: tuple[float, float], ok: list[float], failing: list[float]) -> tuple[float, float]:
    """`full` (low, high) of one dimension narrowed away from its `failing` values, towards `ok` ones."""
    low, high = full
    above = [v for v in failing if not ok or v > max(ok)]
    below = [v for v in failing if ok and v < min(ok)]
    if above:
        high = (max(ok, default=low) + min(above)) / 2
    if below:
        low = (max(below) + min(ok)) / 2
    low, high = max(low, full[0]), min(high, full[1])
    return (low, high) if low <= high else full  # values outside `full` (e.g. stale memory): no shrink


def _excess(value: float, ok: list[float], full: tuple[float, float]) -> float:
    """How far `value` lies outside the `ok` values, as a fraction of the width of `full`."""
    width = (full[1] - full[0]) or 1.0
    return max(value - max(ok), min(ok) - value, 0.0) / width
