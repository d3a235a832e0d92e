"""Run one task of the simulate stage, in this process or in a worker process, and return a picklable result.

A task's episodes depend only on the params, its index and the outcomes already filed under its own
task key (the CoveragePlanner reads no other key), so tasks can run in separate processes and the
caller merges their results in task order. This module imports only what a worker needs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from wc.agent.memory import FailureMemory, Outcome
from wc.agent.planner import CoveragePlanner
from wc.agent.runner import AgentConfig, EpisodeRecord, build_task_world, run_episodes
from wc.config import load_section
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


def run_task(params: dict[str, Any], task_index: int, task_key: str, history: Sequence[Outcome],
             deadline: float | None = None) -> TaskResult:
    """Run task `agent.tasks[task_index]` until it has its accepted episodes or runs out of attempts.
    `history`: the memory's outcomes under `task_key` when the task starts (what its planner learns from)."""
    started = time.perf_counter()
    scene_cfg = load_section(params, "scene", SceneConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    agent_cfg = load_section(params, "agent", AgentConfig)
    validate_cfg = load_section(params, "validate", ValidateConfig)
    task = get_task(agent_cfg.tasks[task_index], params)
    world = build_task_world(scene_cfg, sim_cfg, task)
    planner = CoveragePlanner(FailureMemory(None, history), {task.name: task_key})
    records = list(run_episodes(world, planner, task_index, agent_cfg.episodes_per_task,
                                agent_cfg.max_attempts_per_task, agent_cfg.seed, validate_cfg, deadline=deadline))
    return TaskResult(task.name, records, planner.coverage(task), world.solver_steps,
                      time.perf_counter() - started, float(world.scene.table.top_z))


def init_worker(torch_threads: int) -> None:
    """Worker start-up: the parent's torch thread count, so the IK (torch) runs as it would in the parent."""
    torch.set_num_threads(torch_threads)
