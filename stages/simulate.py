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
from wc.agent.planner import CoveragePlanner
from wc.agent.runner import AgentConfig, run_episodes
from wc.config import add_params_arguments, load_section, params_hash, read_params
from wc.data.store import TrajectoryWriter
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import get_task

SECTIONS = ["scene", "sim", "tasks", "agent"]


def simulate(params: dict[str, Any], out: str | Path = "data/source/raw.zarr",
             report: str | Path = "reports/simulate.json") -> dict[str, Any]:
    """Run every configured task's episodes; write the raw store, the report and lift curves beside
    the report (simulate_lift.csv / .png). Returns the report."""
    scene_cfg = load_section(params, "scene", SceneConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    agent_cfg = load_section(params, "agent", AgentConfig)
    tasks = [get_task(name, params) for name in agent_cfg.tasks]
    objects = [name for name in ("bag", "sphere", "cube") if any(name in t.objects for t in tasks)]
    store_scene = build_scene(scene_cfg, objects)
    phash = params_hash(params, SECTIONS)
    planner = CoveragePlanner()
    per_task: dict[str, dict[str, Any]] = {}
    frames = steps = 0
    curves = {}
    started = time.perf_counter()
    with TrajectoryWriter(out, dt=sim_cfg.frame_dt_s, substeps=sim_cfg.substeps, params_hash=phash,
                          created_by="stages.simulate", object_order=list(store_scene.objects),
                          link_names=list(store_scene.link_names), env_names=list(store_scene.env_names)) as writer:
        for name, mesh in store_scene.objects.items():
            material = getattr(sim_cfg, name).__dict__
            writer.add_object(name, mesh.vertices, mesh.faces, mesh.rest_uv, mesh.vertex_area,
                              kind=store_scene.object_kinds[name], tag=mesh.tag, material=material)
        for samples in store_scene.samples:
            writer.add_prescribed(samples.name, samples.local_points, samples.local_normals, samples.tag, samples.body)
        for task_index, task in enumerate(tasks):
            scene = build_scene(scene_cfg, task.objects)
            sim = NewtonSimulator(scene, sim_cfg)
            failures: dict[str, int] = {}
            accepted = 0
            with tqdm(desc=f"simulate {task.name}", unit="frame") as bar:
                for record in run_episodes(scene, task, task_index, sim, planner, agent_cfg.episodes_per_task,
                                           agent_cfg.seed, on_frame=lambda: bar.update(sim.worlds)):
                    spec = record.spec
                    if record.first_failure:
                        failures[record.first_failure] = failures.get(record.first_failure, 0) + 1
                    if record.x is None:  # never simulated: nothing to store
                        continue
                    eid = writer.add_episode(record.x, record.v, record.action, record.link_poses, record.env_poses,
                                       task=spec.task, seed=spec.seed, cell=spec.cell, speed=spec.speed,
                                       amplitude=spec.amplitude, split=None, accepted=record.first_failure is None,
                                       first_failure=record.first_failure, source="simulator")
                    frames += len(record.x)
                    lowest = record.x[..., 2].min(axis=1) - scene.table.top_z
                    curves[eid] = (lowest, f"{task.name} cell {spec.cell}: {record.first_failure or 'accepted'}")
                    accepted += record.first_failure is None
                    bar.set_postfix(accepted=accepted)
            steps += sim.solver_steps
            per_task[task.name] = {"episodes": agent_cfg.episodes_per_task, "accepted": accepted,
                                   "failures": failures, **planner.coverage(task)}
    wall = time.perf_counter() - started
    result = {
        "episodes": sum(t["episodes"] for t in per_task.values()),
        "accepted": sum(t["accepted"] for t in per_task.values()),
        "frames": frames,
        "solver_steps": steps,
        "wall_s": wall,
        "solver_steps_per_s": steps / wall,
        "simulated_s_per_wall_s": steps * sim_cfg.dt_s / wall,
        "params_hash": phash,
        "tasks": per_task,
        "bag_vertices": len(store_scene.objects["bag"].vertices) if "bag" in store_scene.objects else 0,
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
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # tiny IK tensors: one thread is fastest and immune to a busy second core
    result = simulate(read_params(args.params, args.overrides), args.out, args.report)
    print(f"simulate: {result['accepted']}/{result['episodes']} episodes accepted, {result['frames']} frames, "
          f"{result['simulated_s_per_wall_s']:.3f} simulated s per wall s")


if __name__ == "__main__":
    main()
