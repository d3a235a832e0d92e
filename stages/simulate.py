"""Stage `simulate`: run the task programs in the Newton source simulator -> data/source/raw.zarr.

    python -m stages.simulate [--params params.yaml] [--set agent.episodes_per_task=4 ...]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from wc.agent.lift_plot import write_lift_curves
from wc.agent.memory import FailureMemory
from wc.agent.planner import CoveragePlanner
from wc.agent.runner import AgentConfig, build_task_world, run_episodes
from wc.config import add_params_arguments, load_section, params_hash, read_params
from wc.data.store import TrajectoryWriter
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import OBJECT_KINDS, Scene, build_scene
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import Task, get_task
from wc.validate import ValidateConfig

SECTIONS = ["scene", "sim", "tasks", "agent", "validate"]


def task_key(params: dict[str, Any], name: str) -> str:
    """What a task's outcomes depend on: its params, the shared task params, the scene and the physics."""
    tasks = params.get("tasks", {})
    return params_hash({"scene": params.get("scene"), "sim": params.get("sim"),
                        "task": [tasks.get("common"), tasks.get(name)]}, ["scene", "sim", "task"])


def store_scene(scene_cfg: SceneConfig, tasks: list[Task]) -> Scene:
    """Every object any task predicts or holds: the store's objects and prescribed sample sets."""
    objects = [n for n in OBJECT_KINDS if any(n in t.objects for t in tasks)]
    held: dict[str, tuple] = {}
    for task in tasks:
        held.update(task.held())
    return build_scene(scene_cfg, objects, held={n: held[n] for n in OBJECT_KINDS if n in held})


def simulate(params: dict[str, Any], out: str | Path = "data/source/raw.zarr",
             report: str | Path = "reports/simulate.json",
             memory: str | Path | None = "data/agent/memory.json") -> dict[str, Any]:
    """Run every configured task until it has its accepted episodes (or runs out of attempts); write
    the raw store (accepted and rejected episodes), the report, lift curves beside the report
    (simulate_lift.csv / .png), and append the outcomes to the agent's failure memory (None: none)."""
    scene_cfg = load_section(params, "scene", SceneConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    agent_cfg = load_section(params, "agent", AgentConfig)
    validate_cfg = load_section(params, "validate", ValidateConfig)
    tasks = [get_task(name, params) for name in agent_cfg.tasks]
    union = store_scene(scene_cfg, tasks)
    phash = params_hash(params, SECTIONS)
    outcomes = FailureMemory.load(memory) if memory is not None else FailureMemory()
    planner = CoveragePlanner(outcomes, {t.name: task_key(params, t.name) for t in tasks})
    per_task: dict[str, dict[str, Any]] = {}
    frames = steps = 0
    curves = {}
    started = time.perf_counter()
    with TrajectoryWriter(out, dt=sim_cfg.frame_dt_s, substeps=sim_cfg.substeps, params_hash=phash,
                          created_by="stages.simulate", object_order=list(union.objects),
                          link_names=list(union.link_names), env_names=list(union.env_names)) as writer:
        writer.add_scene(union, {name: getattr(sim_cfg, name).__dict__ for name in union.objects})
        for task_index, task in enumerate(tasks):
            task_started = time.perf_counter()
            world = build_task_world(scene_cfg, sim_cfg, task)
            failures: dict[str, int] = {}
            accepted = episodes = task_frames = 0
            with tqdm(desc=f"simulate {task.name}", unit="frame") as bar:
                for record in run_episodes(world, planner, task_index, agent_cfg.episodes_per_task,
                                           agent_cfg.max_attempts_per_task, agent_cfg.seed, validate_cfg,
                                           on_frame=lambda: bar.update(world.sim.worlds)):
                    spec, episodes = record.spec, episodes + 1
                    if record.first_failure:
                        failures[record.first_failure] = failures.get(record.first_failure, 0) + 1
                    if record.x is None:  # never simulated, or not storable
                        continue
                    eid = writer.add_episode(record.x, record.v, record.action, record.link_poses, record.env_poses,
                                             task=spec.task, seed=spec.seed, cell=spec.cell, speed=spec.speed,
                                             amplitude=spec.amplitude, split=None,
                                             accepted=record.first_failure is None,
                                             first_failure=record.first_failure, failure_frame=record.failure_frame,
                                             source="simulator", **record.layout)
                    task_frames += len(record.x)
                    lowest = record.x[..., 2].min(axis=1) - world.scene.table.top_z
                    curves[eid] = (lowest, f"{task.name} cell {spec.cell}: {record.first_failure or 'accepted'}")
                    accepted += record.first_failure is None
                    bar.set_postfix(accepted=accepted)
            frames += task_frames
            steps += world.solver_steps
            per_task[task.name] = {"episodes": episodes, "accepted": accepted, "frames": task_frames,
                                   "wall_s": time.perf_counter() - task_started, "failures": failures,
                                   **planner.coverage(task)}
            if memory is not None:
                outcomes.save()  # after every task: an interrupted run keeps what it learnt
    wall = time.perf_counter() - started
    result = {
        "episodes": sum(t["episodes"] for t in per_task.values()),
        "accepted": sum(t["accepted"] for t in per_task.values()),
        "tasks_with_accepted": sum(t["accepted"] > 0 for t in per_task.values()),
        "frames": frames,
        "solver_steps": steps,
        "wall_s": wall,
        "episodes_per_min": 60.0 * sum(t["episodes"] for t in per_task.values()) / wall,
        "solver_steps_per_s": steps / wall,
        "simulated_s_per_wall_s": steps * sim_cfg.dt_s / wall,
        "params_hash": phash,
        "tasks": per_task,
        "bag_vertices": len(union.objects["bag"].vertices) if "bag" in union.objects else 0,
        "memory": {"path": str(memory) if memory is not None else None, "outcomes": len(outcomes)},
        "environment": environment_info(NewtonSimulator.device_name(sim_cfg)),
    }
    report = Path(report)
    write_lift_curves(curves, sim_cfg.frame_dt_s, report.with_name("simulate_lift.csv"),
                      report.with_name("simulate_lift.png"))
    write_json_atomic(report, result)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--out", default="data/source/raw.zarr")
    parser.add_argument("--report", default="reports/simulate.json")
    parser.add_argument("--memory", default="data/agent/memory.json",
                        help="the agent's failure memory, read and appended to ('' for none)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # tiny IK tensors: one thread is fastest and immune to a busy second core
    result = simulate(read_params(args.params, args.overrides), args.out, args.report, args.memory or None)
    print(f"simulate: {result['accepted']}/{result['episodes']} episodes accepted "
          f"({result['tasks_with_accepted']}/{len(result['tasks'])} tasks), {result['frames']} frames, "
          f"{result['simulated_s_per_wall_s']:.3f} simulated s per wall s")


if __name__ == "__main__":
    main()
