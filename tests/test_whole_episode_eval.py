"""Whole-episode held-out evaluation: motion phases read from an episode's actions (wc.eval.motion_phases), the
rollouts planned over them (wc.eval.rollout_plan) and the per-task ratio summary (wc.eval.task_ratios)."""

from __future__ import annotations

import numpy as np
import pytest

from wc.eval.motion_phases import PHASE_NAMES, MotionPhase, frame_labels, motion_phases, phase_starts
from wc.eval.rollout_plan import CHART, EPISODE, plan_rollouts
from wc.eval.task_ratios import error_ratio, task_ratios
from wc.train.data import Phase

# (phase, frames, what the program does): a grasp-lift-hold-release episode as a task program writes it
PROGRAM = [("approach", 6, "move"), ("grasp", 4, "close"), ("lift", 7, "move"), ("hold", 5, "still"),
           ("release", 4, "open"), ("drop", 6, "still")]


def program_actions(program=PROGRAM, seed: int = 0) -> np.ndarray:
    """Actions (T, 14) of a synthetic episode: arm joints move, grippers close and open, with IK-sized jitter
    (below the stillness threshold) on held poses."""
    rng = np.random.default_rng(seed)
    a = np.zeros(14)
    a[[6, 13]] = 0.04
    rows = [a.copy()]
    for _, frames, what in program:
        for _ in range(frames):
            a = a.copy()
            a[[0, 1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 12]] += rng.normal(0, 2e-5, 12)  # IK jitter
            if what == "move":
                a[[1, 2, 8]] += 0.01
            elif what == "close":
                a[6] -= 0.008
            elif what == "open":
                a[6] += 0.008
            rows.append(a)
    return np.asarray(rows[:-1], np.float32)  # frame t's label is the step t -> t+1: T = sum of frames


def test_motion_phases_tile_a_synthetic_episode_and_find_every_phase():
    actions = program_actions()
    phases = motion_phases(actions)
    assert [p.name for p in phases] == [name for name, _, _ in PROGRAM] == list(PHASE_NAMES)
    assert phases[0].start == 0 and phases[-1].stop == len(actions)
    assert all(a.stop == b.start for a, b in zip(phases, phases[1:]))
    lengths = [p.stop - p.start for p in phases]
    assert lengths[:-1] == [frames for _, frames, _ in PROGRAM][:-1]  # the last step's label carries to frame T-1


def test_phase_windows_give_a_rollout_start_in_every_phase():
    """Planted bug caught: evenly spaced starts over the frames (not the phases) miss the short grasp and release."""
    phases = motion_phases(program_actions())
    starts = phase_starts(phases, 0, phases[-1].stop, len(PHASE_NAMES))
    assert [name for _, name in starts] == list(PHASE_NAMES)
    assert [frame for frame, _ in starts] == [p.start for p in phases]
    mid = phase_starts(phases, 8, 20, 10)  # a held-out block inside the episode: its phases, clipped to it
    assert mid == [(8, "grasp"), (10, "lift"), (17, "hold")]
    assert phase_starts(phases, 0, phases[-1].stop, 1) == [(phases[3].start, "hold")]  # one: the middle phase
    assert phase_starts(phases, 0, phases[-1].stop, 0) == []


def test_an_episode_without_grip_is_one_approach_and_bad_actions_are_named():
    still = np.zeros((5, 14), np.float32)
    assert motion_phases(still) == [MotionPhase("approach", 0, 5)]
    assert frame_labels(still[:1]) == ["approach"]
    with pytest.raises(ValueError, match=r"\(T >= 1, 14\)"):
        frame_labels(np.zeros((5, 7)))


class ActionStore:
    """The part of a TrajectoryStore the plan reads: episode actions."""

    def __init__(self, actions: dict[str, np.ndarray]) -> None:
        self.actions = actions

    def read_episode(self, eid, fields):  # noqa: ANN001, ANN201 - TrajectoryStore.read_episode's signature
        assert list(fields) == ["action"]
        return {"action": self.actions[eid]}


def test_plan_rolls_out_each_span_whole_and_from_its_phases_and_charts_short_rollouts():
    actions = program_actions()
    store = ActionStore({"e": actions})
    whole = Phase("e", 0, len(actions), ((), ()))
    block = Phase("e", 8, 20, ((), ()))
    plan = plan_rollouts(store, [whole, block, Phase("e", 3, 4, ((), ()))], rollout_frames=12, episode_frames=250,
                         starts_per_span=6, chart={whole, block})
    spans = [(p.span, p.start, p.frames, p.label) for p in plan]
    assert spans[0] == (whole, 0, len(actions), EPISODE)  # the whole episode, capped by its length
    assert spans[1] == (whole, 0, 13, CHART)  # the chart times rollout_frames steps, not the whole episode
    assert [s[3] for s in spans[2:8]] == list(PHASE_NAMES) and all(s[2] <= 13 for s in spans[2:8])
    assert spans[8] == (block, 8, 12, EPISODE)
    assert [s[3] for s in spans[9:]] == ["grasp", "lift", "hold"]  # no CHART: the block's whole rollout is short
    assert len(plan) == 12  # the one-frame span has no rollout
    charted = [p for p in plan if p.charted({whole, block}, 12)]
    assert [(p.span, p.label) for p in charted] == [(whole, CHART), (block, EPISODE)]
    assert plan_rollouts(store, [block], 5, 250, 0, {block})[1].label == CHART  # 11 steps: more than the chart's 5
    assert plan_rollouts(store, [block], 5, 5, 0, {block})[0].charted({block}, 5)  # a block of 12: the whole one


def test_the_summary_is_the_mean_of_per_task_ratios_not_the_pooled_one():
    """Planted bug caught: one task whose errors dwarf the others (a grasp that carries 97 % of the error) makes the
    pooled ratio 20x; the mean of per-task ratios stays near the typical task's 1.8x."""
    per_task = {"worldcontact": {"grasp": 1e-4, "lift": 2.0e-5, "drop": 4.5e-5},
                "robocraft": {"grasp": 5e-3, "lift": 3.6e-5, "drop": None},  # diverged on drop
                "zero_motion": {"grasp": 4e-3, "lift": 3.5e-5, "drop": 5.4e-5}}
    pooled = {"worldcontact": 5.5e-5, "robocraft": None, "zero_motion": 1.36e-3}
    r = task_ratios(per_task, pooled, "worldcontact", ["robocraft", "zero_motion"])
    assert r["per_task"]["grasp"]["best_baseline"] == "zero_motion" and r["per_task"]["grasp"]["ratio"] == pytest.approx(40)
    assert r["per_task"]["lift"]["ratio"] == pytest.approx(1.75)
    assert r["per_task"]["drop"]["best_baseline"] == "zero_motion"  # a diverged baseline is never the best
    assert r["mean_task_ratio"] == pytest.approx((40 + 1.75 + 1.2) / 3)
    assert r["worst_task_ratio"] == pytest.approx(1.2)
    assert r["pooled_ratio"] == pytest.approx(1.36e-3 / 5.5e-5)
    per_task["worldcontact"]["grasp"] = None  # the subject diverged on a task: ratio 0, and the worst
    r = task_ratios(per_task, pooled, "worldcontact", ["robocraft", "zero_motion"])
    assert r["per_task"]["grasp"]["ratio"] == 0.0 and r["worst_task_ratio"] == 0.0
    assert np.isnan(error_ratio(None, None)) and error_ratio(1.0, 0.0) == float("inf")
    with pytest.raises(ValueError, match="missing"):
        task_ratios(per_task, pooled, "worldcontact", [])
