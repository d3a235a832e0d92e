"""The agent's failure memory and the coverage planner that learns from it; a fake task, no simulation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from wc.agent.memory import SCHEMA, FailureMemory, Outcome
from wc.agent.planner import CoveragePlanner, shrunk_range, shrunk_ranges
from wc.tasks.base import EpisodeSpec

SPEEDS = (0.1, 1.0)
AMPLITUDES = (0.1, 0.2)


class FakeTask:
    """Three cells; any speed above 0.5 fails in cell 0, everything else passes."""

    name = "fake"
    objects = ()

    def __init__(self, cells: int = 3) -> None:
        self.cells = cells

    def num_cells(self) -> int:
        return self.cells

    def speed_range(self) -> tuple[float, float]:
        return SPEEDS

    def amplitude_range(self) -> tuple[float, float]:
        return AMPLITUDES


def verdict(spec: EpisodeSpec) -> str | None:
    return "blow_up" if spec.cell == 0 and spec.speed > 0.5 else None


def run(planner: CoveragePlanner, task: FakeTask, seeds) -> list[EpisodeSpec]:
    """Propose, judge and record one episode per seed, as wc.agent.runner does."""
    specs = []
    for seed in seeds:
        spec = planner.propose(task, seed)
        planner.record(spec, verdict(spec))
        specs.append(spec)
    return specs


def spec(cell: int, speed: float, amplitude: float = 0.15, seed: int = 0) -> EpisodeSpec:
    return EpisodeSpec("fake", seed, cell, speed, amplitude)


def memory_with(path, *outcomes: tuple[EpisodeSpec, str | None], key: str = "fake") -> FailureMemory:
    memory = FailureMemory(path)
    for s, failure in outcomes:
        memory.record(key, s, failure)
    return memory


# -- the memory file


def test_memory_round_trips_through_its_file(tmp_path):
    path = tmp_path / "agent" / "memory.json"
    memory = FailureMemory.load(path)
    assert len(memory) == 0 and not path.exists()
    memory.record("k1", spec(0, 0.8, 0.12, seed=7), "blow_up", failure_frame=31)
    memory.record("k1", spec(1, 0.3), None)
    memory.record("k2", spec(0, 0.4), None)
    memory.save()
    assert json.loads(path.read_text())["schema"] == SCHEMA
    assert not [p.name for p in path.parent.iterdir() if p.name != "memory.json"], "temporary file left behind"
    again = FailureMemory.load(path)
    assert again.outcomes("k1") == memory.outcomes("k1") == [
        Outcome("fake", "k1", 0, 0.8, 0.12, 7, "blow_up", 31), Outcome("fake", "k1", 1, 0.3, 0.15, 0, None, None)]
    assert again.outcomes("k1", cell=1) == [Outcome("fake", "k1", 1, 0.3, 0.15, 0, None, None)]
    assert again.visits("k1") == {0: 1, 1: 1} and again.accepted("k1") == {1: 1}
    assert again.outcomes("k2") == [Outcome("fake", "k2", 0, 0.4, 0.15, 0, None, None)]
    again.record("k1", spec(2, 0.5), None)  # append-only: the old outcomes stay
    again.save()
    assert len(FailureMemory.load(path)) == 4


@pytest.mark.parametrize("text, message", [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "not an agent memory file"),
    (json.dumps({"schema": "something-else/1", "outcomes": []}), "not an agent memory file"),
    (json.dumps({"schema": SCHEMA, "outcomes": {}}), "'outcomes' must be a list"),
    (json.dumps({"schema": SCHEMA, "outcomes": [{"task": "fake"}]}), r"outcomes\[0\]: .*missing keys"),
    (json.dumps({"schema": SCHEMA, "outcomes": [
        {"task": "fake", "task_key": "k", "cell": 0, "speed": "fast", "amplitude": 0.1, "seed": 0,
         "failure": None}]}), r"outcomes\[0\]\.speed has the wrong type"),
    (json.dumps({"schema": SCHEMA, "outcomes": [
        {"task": "fake", "task_key": "k", "cell": True, "speed": 0.2, "amplitude": 0.1, "seed": 0,
         "failure": None}]}), r"outcomes\[0\]\.cell has the wrong type"),
])
def test_malformed_memory_file_fails_naming_the_file(tmp_path, text, message):
    path = tmp_path / "memory.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as err:
        FailureMemory.load(path)
    assert str(path) in str(err.value)


def test_memory_without_a_file_cannot_be_saved():
    with pytest.raises(ValueError, match="no file"):
        FailureMemory().save()


# -- range shrinking: the exact rule


def test_shrunk_range_bisects_towards_the_boundary():
    assert shrunk_range(SPEEDS, [], []) == SPEEDS
    assert shrunk_range(SPEEDS, [], [0.8, 0.9]) == pytest.approx((0.1, 0.45))  # no success: (low + 0.8) / 2
    assert shrunk_range(SPEEDS, [0.3, 0.4], [0.8]) == pytest.approx((0.1, 0.6))  # (highest success + 0.8) / 2
    assert shrunk_range(SPEEDS, [0.5], [0.2]) == pytest.approx((0.35, 1.0))  # failures below every success
    assert shrunk_range(SPEEDS, [0.3, 0.9], [0.5]) == SPEEDS  # a failure between successes: no shrink


def test_a_failure_narrows_only_the_dimension_it_lies_farthest_out_in():
    # speed 0.9 is 0.67 of the speed range above the success, amplitude 0.15 only 0.3 of its range
    speed, amplitude = shrunk_ranges((SPEEDS, AMPLITUDES), [(0.3, 0.12), (0.9, 0.15)], [False, True])
    assert speed == pytest.approx((0.1, 0.6)) and amplitude == AMPLITUDES
    speed, amplitude = shrunk_ranges((SPEEDS, AMPLITUDES), [(0.3, 0.11), (0.4, 0.19)], [False, True])
    assert speed == SPEEDS and amplitude == pytest.approx((0.1, 0.15))
    # no success yet: the failure might be either's fault, so both narrow
    speed, amplitude = shrunk_ranges((SPEEDS, AMPLITUDES), [(0.9, 0.15)], [True])
    assert speed == pytest.approx((0.1, 0.5)) and amplitude == pytest.approx((0.1, 0.125))


# -- the planner


def test_memory_changes_what_is_sampled_after_a_failure(tmp_path):
    task = FakeTask(cells=1)
    fresh = CoveragePlanner().propose(task, 5)
    failed = spec(0, fresh.speed, fresh.amplitude, seed=5)
    assert verdict(failed) == "blow_up", "seed 5 must draw a failing speed for this test to mean anything"
    informed = CoveragePlanner(memory_with(tmp_path / "m.json", (failed, "blow_up"))).propose(task, 5)
    assert informed.cell == 0
    assert informed.speed <= (SPEEDS[0] + failed.speed) / 2  # drawn from the shrunk ranges
    assert informed.amplitude <= (AMPLITUDES[0] + failed.amplitude) / 2
    assert (informed.speed, informed.amplitude) != (failed.speed, failed.amplitude)


def test_a_failed_sample_is_never_proposed_again(tmp_path):
    task = FakeTask(cells=1)
    fresh = CoveragePlanner().propose(task, 11)
    # successes at both ends of both ranges, so the failure shrinks nothing: only the retry rule acts
    memory = memory_with(tmp_path / "m.json", (spec(0, 0.1, 0.1), None), (spec(0, 1.0, 0.2), None),
                         (spec(0, fresh.speed, fresh.amplitude, seed=11), "self_intersection"))
    again = CoveragePlanner(memory).propose(task, 11)
    assert abs(again.speed - fresh.speed) > 1e-3 or abs(again.amplitude - fresh.amplitude) > 1e-3


def test_forced_failures_in_one_cell_shrink_its_speeds_and_keep_it_covered():
    task = FakeTask()
    planner = CoveragePlanner()
    specs = run(planner, task, range(60))
    cell0 = [s for s in specs if s.cell == 0]
    failures = [s for s in cell0 if verdict(s)]
    assert failures, "the forced failure must happen for this test to mean anything"
    for i, s in enumerate(cell0):  # every later proposal lies below every earlier failing speed
        earlier = [f.speed for f in cell0[:i] if verdict(f)]
        assert not earlier or s.speed < min(earlier)
    assert len(failures) <= 3 and len(cell0) - len(failures) >= 15
    assert max(s.amplitude for s in cell0) > failures[0].amplitude  # speed failures leave amplitudes alone
    assert planner.coverage(task) == {"cells": 3, "cells_visited": 3, "cells_accepted": 3,
                                      "cells_visited_all_runs": 3, "cells_accepted_all_runs": 3,
                                      "cells_given_up": 0}


def test_memoryless_planner_fails_more_in_the_forced_cell():
    """The baseline the memory improves on: the old uniform sampling, same seeds."""
    # without memory cell 0 gets every third seed, and a speed drawn first from the seed's generator
    uniform_failures = sum(np.random.default_rng(seed).uniform(*SPEEDS) > 0.5 for seed in range(0, 60, 3))
    informed = [s for s in run(CoveragePlanner(), FakeTask(), range(60)) if s.cell == 0 and verdict(s)]
    assert len(informed) < uniform_failures


def test_under_covered_cells_are_proposed_first(tmp_path):
    memory = memory_with(tmp_path / "m.json", (spec(0, 0.2), None), (spec(0, 0.3), None), (spec(1, 0.2), None),
                         (spec(2, 0.2), "penetration"))
    planner = CoveragePlanner(memory)
    # a batch proposed before any verdict: fewest accepted (in-flight counted as accepted), then fewest visits
    assert [planner.propose(FakeTask(), seed).cell for seed in range(4)] == [2, 1, 2, 0]
    fresh = CoveragePlanner()
    assert [fresh.propose(FakeTask(), seed).cell for seed in range(4)] == [0, 1, 2, 0]


def test_a_cell_that_keeps_failing_is_deprioritised(tmp_path):
    failures = [(spec(0, 0.9 - 0.1 * i), "blow_up") for i in range(3)]
    successes = [(spec(c, 0.2), None) for c in (1, 2) for _ in range(5)]
    memory = memory_with(tmp_path / "m.json", *failures, *successes)
    assert CoveragePlanner(memory).propose(FakeTask(), 0).cell == 1
    assert CoveragePlanner(memory, give_up_after=4).propose(FakeTask(), 0).cell == 0
    assert CoveragePlanner(memory).coverage(FakeTask())["cells_given_up"] == 1
    memory.record("fake", spec(0, 0.2), None)  # one success and the cell is back in line
    assert CoveragePlanner(memory).propose(FakeTask(), 0).cell == 0


def test_memory_persists_across_runs(tmp_path):
    path = tmp_path / "agent" / "memory.json"
    task = FakeTask()
    first = CoveragePlanner(FailureMemory.load(path))
    run(first, task, range(7))
    first.memory.save()
    assert first.coverage(task)["cells_accepted"] == 3

    second = CoveragePlanner(FailureMemory.load(path))
    assert second.coverage(task) == {"cells": 3, "cells_visited": 0, "cells_accepted": 0,
                                     "cells_visited_all_runs": 3, "cells_accepted_all_runs": 3,
                                     "cells_given_up": 0}
    later = range(100, 112)
    assert run(second, task, later) == run(first, task, later)  # the same informed choices as the first run's
    assert run(CoveragePlanner(), task, later) != run(CoveragePlanner(FailureMemory.load(path)), task, later)
    second.memory.save()
    assert len(FailureMemory.load(path)) == 7 + 12


def test_a_fresh_run_ignores_the_file_and_rewrites_it_a_kept_run_learns_from_it(tmp_path):
    path = tmp_path / "memory.json"
    first = CoveragePlanner(FailureMemory.for_run(path, "fresh"))
    run(first, FakeTask(), range(9))
    first.memory.save()
    later = range(50, 80)
    fresh = CoveragePlanner(FailureMemory.for_run(path, "fresh"))
    assert run(fresh, FakeTask(), later) == run(CoveragePlanner(), FakeTask(), later)  # as if no earlier run
    kept = CoveragePlanner(FailureMemory.for_run(path, "kept"))
    assert len(kept.memory) == 9 and run(kept, FakeTask(), later) != run(CoveragePlanner(), FakeTask(), later)
    fresh.memory.save()
    assert len(FailureMemory.load(path)) == 30  # the fresh run's outcomes alone
    with pytest.raises(ValueError, match="fresh or kept, got 'old'"):
        FailureMemory.for_run(path, "old")


def test_same_seeds_and_memory_give_the_same_proposals(tmp_path):
    path = tmp_path / "memory.json"
    run(CoveragePlanner(FailureMemory(path)), FakeTask(), range(9))  # not saved: nothing persists
    assert not path.exists()
    seeded = CoveragePlanner(FailureMemory(path))
    run(seeded, FakeTask(), range(9))
    seeded.memory.save()
    a = run(CoveragePlanner(FailureMemory.load(path)), FakeTask(), range(50, 80))
    b = run(CoveragePlanner(FailureMemory.load(path)), FakeTask(), range(50, 80))
    assert a == b


def test_outcomes_under_another_task_key_are_ignored(tmp_path):
    path = tmp_path / "memory.json"
    stale = [(spec(0, 0.6 + 0.1 * i), "blow_up") for i in range(3)] + [(spec(1, 0.2), None), (spec(2, 0.2), None)]
    memory_with(path, *stale, key="fake@old-params").save()
    seeds = range(20, 26)
    baseline = run(CoveragePlanner(), FakeTask(), seeds)
    other_key = CoveragePlanner(FailureMemory.load(path), task_keys={"fake": "fake@new-params"})
    assert run(other_key, FakeTask(), seeds) == baseline
    same_key = CoveragePlanner(FailureMemory.load(path), task_keys={"fake": "fake@old-params"})
    assert run(same_key, FakeTask(), seeds) != baseline
    assert other_key.coverage(FakeTask())["cells_accepted_all_runs"] == 3  # its own run only
    assert {o.task_key for o in other_key.memory.outcomes("fake@new-params")} == {"fake@new-params"}


def test_unknown_task_key_and_bad_arguments_fail_clearly():
    with pytest.raises(KeyError, match="no task key for task 'fake'"):
        CoveragePlanner(task_keys={"lift_handle": "abc"}).propose(FakeTask(), 0)
    with pytest.raises(ValueError, match="give_up_after must be >= 1"):
        CoveragePlanner(give_up_after=0)
