"""The data-generation agent: Reset -> Execute -> Validate -> Accept, several episodes per batch."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from wc.agent.planner import Planner
from wc.scene.scene import Scene
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import EpisodeSpec, InfeasibleEpisode, Task


@dataclass(frozen=True)
class AgentConfig:
    tasks: tuple[str, ...]  # task programs to run, by registered name
    episodes_per_task: int
    seed: int  # stage seed; episode seeds derive from it

    def validate(self) -> None:
        if not self.tasks:
            raise ValueError("tasks must name at least one task")
        if self.episodes_per_task < 1:
            raise ValueError(f"episodes_per_task must be >= 1, got {self.episodes_per_task}")


@dataclass
class EpisodeRecord:
    """One executed episode; arrays are None when it could not be planned (first_failure 'unreachable')."""

    spec: EpisodeSpec
    first_failure: str | None
    x: np.ndarray | None = None  # (T, N, 3)
    v: np.ndarray | None = None
    action: np.ndarray | None = None  # (T, 14)
    link_poses: np.ndarray | None = None  # (T, L, 7)
    env_poses: np.ndarray | None = None  # (T, E, 7)


def episode_seed(stage_seed: int, task_index: int, episode_index: int) -> int:
    """One independent seed per episode, derived from the stage seed."""
    return int(np.random.SeedSequence([stage_seed, task_index, episode_index]).generate_state(1)[0])


def first_failure(scene: Scene, task: Task, x: np.ndarray, v: np.ndarray, action: np.ndarray) -> str | None:
    """Name of the first failing check of a simulated episode, or None if it passes."""
    if not (np.isfinite(x).all() and np.isfinite(v).all()):
        return "non_finite"
    check = getattr(task, "check", None)
    return check(scene, x, action) if check is not None else None


def pad_to_length(actions: np.ndarray, length: int) -> np.ndarray:
    """Hold the last action until the episode has `length` frames."""
    return np.concatenate([actions, np.repeat(actions[-1:], length - len(actions), axis=0)])


def run_episodes(scene: Scene, task: Task, task_index: int, sim: NewtonSimulator, planner: Planner,
                 count: int, stage_seed: int, on_frame: Callable[[], None] | None = None) -> Iterator[EpisodeRecord]:
    """Simulate `count` episodes of one task, `sim.worlds` at a time, yielding each with its verdict."""
    for first in range(0, count, sim.worlds):
        specs = [planner.propose(task, episode_seed(stage_seed, task_index, i))
                 for i in range(first, min(count, first + sim.worlds))]
        planned = []
        for spec in specs:  # Reset
            try:
                initial = task.initial_state(scene, spec, np.random.default_rng(spec.seed))
                planned.append((spec, initial, task.settle_action(scene, spec, initial)))
            except InfeasibleEpisode:
                planner.record(spec, "unreachable")
                yield EpisodeRecord(spec, "unreachable")
        if not planned:
            continue
        settled = sim.settle([p[1] for p in planned], [p[2] for p in planned], sim.cfg.settle_s)
        runnable = []
        for (spec, _, held), state in zip(planned, settled):
            try:
                runnable.append((spec, state, task.actions(scene, state, spec, held, sim.cfg.frame_dt_s)))
            except InfeasibleEpisode:
                planner.record(spec, "unreachable")
                yield EpisodeRecord(spec, "unreachable")
        if not runnable:
            continue
        length = max(len(r[2]) for r in runnable)
        actions = [pad_to_length(r[2], length) for r in runnable]
        results = sim.rollout_batch([r[1] for r in runnable], actions, on_frame=on_frame)  # Execute
        env = np.repeat(scene.env_poses()[None], length, axis=0)
        for (spec, _, _), act, (x, v) in zip(runnable, actions, results):
            failure = first_failure(scene, task, x, v, act)  # Validate
            planner.record(spec, failure)
            yield EpisodeRecord(spec, failure, x, v, act, scene.link_poses(act), env)  # Accept (or log)
