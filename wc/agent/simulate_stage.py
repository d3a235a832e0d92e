"""The simulate stage's work (`python -m stages.simulate`): the task programs run in the Newton source simulator,
one after another or in spawned worker processes -> the raw store (data/source/raw.zarr), the report and the agent's
failure memory.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Future, wait
from contextlib import closing
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from wc.agent.lift_plot import write_lift_curves
from wc.agent.memory import FailureMemory
from wc.agent.parallel import TaskResult, init_worker, run_task, task_attempts, task_result
from wc.agent.runner import AgentConfig, simulator_store
from wc.config import load_section, params_hash, without_keys
from wc.data.store import TrajectoryWriter
from wc.distributed import Executor, UnitsFailed, drive, every_unit, open_executor, uses_cuda
from wc.paths import SIMULATE
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import get_task
from wc.validate import ValidateConfig
from wc.worker_pool import spawn_pool

SECTIONS = ["scene", "sim", "tasks", "agent", "validate"]


def task_key(params: dict[str, Any], name: str) -> str:
    """What a task's outcomes depend on: its params, the shared task params, the scene and the physics."""
    tasks = params.get("tasks", {})
    return params_hash({"scene": params.get("scene"), "sim": params.get("sim"),
                        "task": [tasks.get("common"), tasks.get(name)]}, ["scene", "sim", "task"])


def output_params(params: dict[str, Any]) -> dict[str, Any]:
    """`params` without agent.workers and agent.executor: where the tasks run does not change the output."""
    return without_keys(params, "agent", ("workers", "executor"))


def task_results(params: dict[str, Any], keys: dict[str, str], memory: FailureMemory,
                 workers: int, deadline: float | None = None,
                 executor: Executor | None = None) -> Iterator[TaskResult]:
    """Each task's result, in task order (`keys`: task name -> task key). A task starts from the outcomes
    `memory` holds under its key when it starts. A ray or processes `executor`: every task's batches as its units,
    the tasks' planners here (keys must differ); else workers == 1: one after another in this process; else in that
    many spawned worker processes, at most `workers` tasks in flight."""
    names = list(keys)
    if executor is not None and executor.name != "local":
        streams = [task_attempts(params, i, keys[name], memory.outcomes(keys[name]), deadline)
                   for i, name in enumerate(names)]
        for i in drive(executor, streams, load_section(params, "agent", AgentConfig).batches_in_flight):
            yield task_result(streams[i], streams[i].wall_s)
        return
    if workers == 1:
        for index, name in enumerate(names):
            try:
                yield run_task(params, index, keys[name], memory.outcomes(keys[name]), deadline)
            except Exception as err:
                err.add_note(f"while simulating task {name!r}")
                raise
        return
    # spawned workers that end with this process; kernels come from ~/.cache/warp
    with spawn_pool(min(workers, len(names)), init_worker, (torch.get_num_threads(),)) as pool:
        waiting = deque(range(len(names)))  # task order: their costs are not known in advance
        running: dict[Future[TaskResult], int] = {}
        finished: dict[int, TaskResult] = {}
        for index in range(len(names)):
            while index not in finished:
                while waiting and len(running) < workers:
                    i = waiting.popleft()
                    running[pool.submit(run_task, params, i, keys[names[i]], memory.outcomes(keys[names[i]]),
                                        deadline)] = i
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in sorted(done, key=running.__getitem__):  # the first failing task in task order
                    i = running.pop(future)
                    try:
                        finished[i] = future.result()
                    except Exception as err:  # the tasks still running are waited for, none is started
                        raise RuntimeError(f"simulate: task {names[i]!r} failed in a worker process: "
                                           f"{type(err).__name__}: {err}") from err
            yield finished.pop(index)


def _file_task(result: TaskResult, key: str, writer: TrajectoryWriter, memory: FailureMemory,
               curves: dict[str, tuple[Any, str]]) -> dict[str, Any]:
    """Write a task's storable episodes, file its outcomes under `key` in `memory`, add its lift curves; returns
    its entry in the report."""
    failures: dict[str, int] = {}
    accepted = frames = 0
    for record in result.records:
        spec = record.spec
        memory.record(key, spec, record.first_failure, record.failure_frame)
        if record.first_failure:
            failures[record.first_failure] = failures.get(record.first_failure, 0) + 1
        if record.x is None:  # never simulated, or not storable
            continue
        eid = writer.add_episode(record.x, record.v, record.action, record.link_poses, record.env_poses,
                                 task=spec.task, seed=spec.seed, cell=spec.cell, speed=spec.speed,
                                 amplitude=spec.amplitude, split=None, accepted=record.first_failure is None,
                                 first_failure=record.first_failure, failure_frame=record.failure_frame,
                                 source="simulator", **record.layout)
        frames += len(record.x)
        lowest = record.x[..., 2].min(axis=1) - result.table_top_z
        curves[eid] = (lowest, f"{result.task} cell {spec.cell}: {record.first_failure or 'accepted'}")
        accepted += record.first_failure is None
    return {"episodes": len(result.records), "accepted": accepted, "frames": frames, "wall_s": result.wall_s,
            "failures": failures, **result.coverage}


def simulate(params: dict[str, Any], out: str | Path = SIMULATE["out"], report: str | Path = SIMULATE["report"],
             memory: str | Path | None = SIMULATE["memory"], max_minutes: float = 0.0) -> dict[str, Any]:
    """Run every configured task until it has its accepted episodes (or runs out of attempts), in
    `agent.workers` processes, on Ray or in device processes (`agent.executor`); write the raw store (accepted and
    rejected episodes, in task order), the report, lift curves beside the report (simulate_lift.csv / .png), and the
    outcomes to the agent's failure memory file (None: none), saved after each task: this run's alone
    (`agent.memory: fresh`) or appended to the file's (`kept`, which the planner then learns from). max_minutes > 0: no batch of episodes starts
    after that wall time (a chunked GPU job; the report's `stopped_early` says so). Ray units that kept failing:
    the report lists them, no store is written, UnitsFailed."""
    scene_cfg = load_section(params, "scene", SceneConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    agent_cfg = load_section(params, "agent", AgentConfig)
    validate_cfg = load_section(params, "validate", ValidateConfig)  # bad input fails before any output
    tasks = [get_task(name, params) for name in agent_cfg.tasks]
    phash = params_hash(output_params(params), SECTIONS)
    keys = {t.name: task_key(params, t.name) for t in tasks}
    if (agent_cfg.workers > 1 or agent_cfg.executor != "local") and len(set(keys.values())) < len(keys):
        raise ValueError("tasks with identical params share their outcomes, so they cannot run in separate "
                         "workers; set agent.workers=1 and agent.executor=local")
    outcomes = FailureMemory.for_run(memory, agent_cfg.memory)
    per_task: dict[str, dict[str, Any]] = {}
    curves: dict[str, tuple[Any, str]] = {}
    started = time.perf_counter()
    deadline = time.time() + 60.0 * max_minutes if max_minutes > 0 else None
    failed, steps, environment = None, 0, None
    with open_executor(agent_cfg.executor, params, uses_cuda(sim_cfg.device, validate_cfg.device)) as executor:
        try:
            with (simulator_store(out, scene_cfg, sim_cfg, tasks, phash, "stages.simulate") as (writer, union),
                  closing(task_results(params, keys, outcomes, agent_cfg.workers, deadline, executor)) as results,
                  tqdm(results, total=len(tasks), desc="simulate", unit="task") as bar,
                  every_unit(executor, "simulate")):
                for result in bar:
                    per_task[result.task] = _file_task(result, keys[result.task], writer, outcomes, curves)
                    steps += result.solver_steps
                    environment = environment or result.environment
                    bar.set_postfix(task=result.task, accepted=sum(t["accepted"] for t in per_task.values()))
                    if memory is not None:
                        outcomes.save()  # after every task: an interrupted run keeps what it learnt
        except UnitsFailed as err:
            failed = err
    wall = time.perf_counter() - started
    episodes = sum(t["episodes"] for t in per_task.values())
    result = {
        "episodes": episodes,
        "accepted": sum(t["accepted"] for t in per_task.values()),
        "tasks_with_accepted": sum(t["accepted"] > 0 for t in per_task.values()),
        "stopped_early": deadline is not None and time.time() >= deadline,
        "frames": sum(t["frames"] for t in per_task.values()),
        "solver_steps": steps,
        "wall_s": wall,
        "episodes_per_min": 60.0 * episodes / wall,
        "solver_steps_per_s": steps / wall,
        "workers": agent_cfg.workers,
        "executor": executor.report(),
        "simulated_s_per_wall_s": steps * sim_cfg.dt_s / wall,
        "params_hash": phash,
        "tasks": per_task,
        "bag_vertices": len(union.objects["bag"].vertices) if "bag" in union.objects else 0,
        "memory": {"path": str(memory) if memory is not None else None, "mode": agent_cfg.memory,
                   "outcomes": len(outcomes)},
        "environment": environment or environment_info(NewtonSimulator.device_name(sim_cfg)
                                                       if agent_cfg.executor == "local" else "cpu"),  # else a worker's
    }
    report = Path(report)
    write_lift_curves(curves, sim_cfg.frame_dt_s, report.with_name("simulate_lift.csv"),
                      report.with_name("simulate_lift.png"))
    write_json_atomic(report, result)
    if failed is not None:
        raise failed
    return result


def run(params: dict[str, Any], out: str | Path = SIMULATE["out"], report: str | Path = SIMULATE["report"],
        memory: str | Path | None = SIMULATE["memory"], max_minutes: float = 0.0) -> dict[str, Any]:
    """`simulate` as the stage runs it: with one torch thread in this process (tiny IK tensors: one thread is
    fastest and immune to a busy second core; the workers get as many)."""
    torch.set_num_threads(1)
    return simulate(params, out, report, memory, max_minutes)


def simulate_summary(result: dict[str, Any]) -> str:
    """The line `python -m stages.simulate` prints."""
    return (f"simulate: {result['accepted']}/{result['episodes']} episodes accepted "
            f"({result['tasks_with_accepted']}/{len(result['tasks'])} tasks), {result['frames']} frames, "
            f"{result['simulated_s_per_wall_s']:.3f} simulated s per wall s")
