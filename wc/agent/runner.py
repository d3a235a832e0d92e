"""The data-generation agent: Reset -> Execute -> Validate -> Accept, several episodes per batch."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from wc.agent.planner import Planner
from wc.scene.scene import Scene
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import EpisodeSpec, Task


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
    spec: EpisodeSpec
    x: np.ndarray  # (T, N, 3)
    v: np.ndarray
    action: np.ndarray  # (T, 14)
    link_poses: np.ndarray  # (T, L, 7)
    env_poses: np.ndarray  # (T, E, 7)
    first_failure: str | None


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
        initial = [task.initial_state(scene, s, np.random.default_rng(s.seed)) for s in specs]  # Reset
        held = [task.settle_action(scene, s, init) for s, init in zip(specs, initial)]
        settled = sim.settle(initial, held, sim.cfg.settle_s)
        actions = [task.actions(scene, st, s, a0, sim.cfg.frame_dt_s) for st, s, a0 in zip(settled, specs, held)]
        length = max(len(a) for a in actions)
        actions = [pad_to_length(a, length) for a in actions]
        results = sim.rollout_batch(settled, actions, on_frame=on_frame)  # Execute
        env = np.repeat(scene.env_poses()[None], length, axis=0)
        for spec, act, (x, v) in zip(specs, actions, results):
            failure = first_failure(scene, task, x, v, act)  # Validate
            planner.record(spec, failure)
            yield EpisodeRecord(spec, x, v, act, scene.link_poses(act), env, failure)  # Accept (or log)
