"""Run one task of the simulate stage, in this process or in a worker process, and return a picklable result.

A task's episodes depend only on the params, its index and the outcomes already filed under its own
task key (the CoveragePlanner reads no other key), so tasks can run in separate processes and the
caller merges their results in task order. Within a task, the planner proposes batches and files their verdicts
(wc.agent.runner.TaskAttempts); a batch is a work unit, simulated by `batch_simulator`'s worker here or, with the
ray executor, in a Ray worker process (wc.agent.ray_tasks). This module imports only what a worker needs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from wc.agent.memory import FailureMemory, Outcome
from wc.agent.planner import CoveragePlanner
from wc.agent.runner import AgentConfig, BatchSimulator, EpisodeRecord, TaskAttempts, build_task_world
from wc.config import load_section, params_hash
from wc.distributed import LocalExecutor, WorkerSpec, drive
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.tasks.base import get_task
from wc.validate import ValidateConfig


@dataclass
class TaskResult:
    """Everything one task produced; the caller writes the episodes and files the outcomes."""

    task: str
    records: list[EpisodeRecord]  # in the order they ran, one per outcome the planner recorded
    coverage: dict[str, int]  # CoveragePlanner.coverage of the task (this run and all runs)
    solver_steps: int
    wall_s: float
    table_top_z: float  # table top height [m], for the lift curves
    environment: dict[str, str] | None = None  # where its batches ran (None: none ran)


def batch_simulator(params: dict[str, Any], task_index: int) -> BatchSimulator:
    """The worker of task `agent.tasks[task_index]`'s simulate work units: its world, built from `params`."""
    agent_cfg = load_section(params, "agent", AgentConfig)
    world = build_task_world(load_section(params, "scene", SceneConfig), load_section(params, "sim", SimConfig),
                             get_task(agent_cfg.tasks[task_index], params))
    return BatchSimulator(world, load_section(params, "validate", ValidateConfig))


def task_attempts(params: dict[str, Any], task_index: int, task_key: str, history: Sequence[Outcome],
                  deadline: float | None = None) -> TaskAttempts:
    """The planner's side of task `agent.tasks[task_index]` (wc.agent.runner.TaskAttempts), its planner learning
    from `history`, the memory's outcomes under `task_key` when the task starts; its units' worker is
    `batch_simulator(params, task_index)`, shared by the runs of the same scene, physics and task params."""
    agent_cfg = load_section(params, "agent", AgentConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    task = get_task(agent_cfg.tasks[task_index], params)
    planner = CoveragePlanner(FailureMemory(None, history), {task.name: task_key})
    worker = WorkerSpec(f"simulate:{task.name}:{params_hash(params, ['scene', 'sim', 'tasks'])}", batch_simulator,
                        (params, task_index))
    return TaskAttempts(task, planner, task_index, sim_cfg.worlds, agent_cfg.episodes_per_task,
                        agent_cfg.max_attempts_per_task, agent_cfg.seed, worker, deadline)


def task_result(attempts: TaskAttempts, wall_s: float) -> TaskResult:
    """A finished task's result, for the caller to write and file."""
    return TaskResult(attempts.task.name, attempts.records, attempts.planner.coverage(attempts.task),
                      attempts.solver_steps, wall_s, attempts.table_top_z, attempts.environment)


def run_task(params: dict[str, Any], task_index: int, task_key: str, history: Sequence[Outcome],
             deadline: float | None = None) -> TaskResult:
    """Run task `agent.tasks[task_index]` in this process until it has its accepted episodes or runs out of
    attempts. `history`: the memory's outcomes under `task_key` when the task starts (what its planner learns from)."""
    started = time.perf_counter()
    attempts = task_attempts(params, task_index, task_key, history, deadline)
    for _ in drive(LocalExecutor(), [attempts], load_section(params, "agent", AgentConfig).batches_in_flight):
        pass
    return task_result(attempts, time.perf_counter() - started)


def init_worker(torch_threads: int) -> None:
    """Worker start-up: the parent's torch thread count, so the IK (torch) runs as it would in the parent."""
    torch.set_num_threads(torch_threads)
