"""Ground truth of the stress cases: the Newton source simulator runs the real task programs with each case's
params overrides, and the episodes go to a trajectory store (data/stress/trajectories.zarr).

Per case, episode draws follow the agent (wc.agent.runner: Reset -> Execute -> Validate) with a fresh
CoveragePlanner and seeds derived from (stress.seed, case index, attempt). The action program is cut to
stress.rollout_frames + 1 frames before it is simulated (the rollouts go no further). An episode is kept as
ground truth when it is physically sane: the non_finite and blow_up checks pass. Every other verdict (a
penetrating pinch, the task's own "not_lifted", ...) is kept and recorded in the episode attrs
(`first_failure`, `accepted`): a stressed episode failing its task is still what the physics did. Episodes that
cannot be planned or are not sane are redrawn, up to stress.max_attempts per case.

The store is reused when it exists and carries the params hash of everything the simulation depends on
(stress cases and overrides, scene, sim, tasks, validate), so a rerun after a model change does not simulate.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from wc.agent.parallel import init_worker
from wc.agent.planner import CoveragePlanner
from wc.agent.runner import (build_task_world, execute, judge, layout_attrs, release_frame, reset_batch,
                             simulator_store)
from wc.config import ParamsError, load_section, params_hash, set_dotted
from wc.data.store import TrajectoryStore
from wc.eval.stress_config import StressConfig
from wc.scene.config import SceneConfig
from wc.seeds import episode_seed
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import UNREACHABLE, get_task
from wc.validate import ValidateConfig
from wc.worker_pool import spawn_pool

TRUTH_SECTIONS = ["stress_truth", "scene", "sim", "tasks", "validate"]
INSANE = ("non_finite", "blow_up")  # first failures that make an episode unusable as ground truth
TCP_LINK = "right_link6"  # whose speed the report gives (every stress task moves the right arm)


def case_params(params: dict[str, Any], cfg: StressConfig, name: str) -> dict[str, Any]:
    """A copy of `params` with stress.overrides, then stress.cases.<name>.overrides, applied (dotted keys)."""
    out = copy.deepcopy(params)
    source = params.get("_source", "<params>")
    for where, overrides in (("stress.overrides", cfg.overrides),
                             (f"stress.cases.{name}.overrides", cfg.cases[name].overrides)):
        for key, value in overrides.items():
            set_dotted(out, key, copy.deepcopy(value), f"{source}: {where}.{key}")
    return out


def truth_hash(params: dict[str, Any], cfg: StressConfig) -> str:
    """Hash of what the ground-truth episodes depend on (not the video or the model rollouts)."""
    truth = {"task": cfg.task, "episodes": cfg.episodes, "max_attempts": cfg.max_attempts,
             "rollout_frames": cfg.rollout_frames, "seed": cfg.seed, "overrides": cfg.overrides,
             "cases": {n: {"task": cfg.case_task(n), "overrides": c.overrides} for n, c in cfg.cases.items()}}
    return params_hash({**params, "stress_truth": truth}, TRUTH_SECTIONS)


def peak_speed_m_s(link_poses: np.ndarray, column: int, dt: float) -> float:
    """Largest frame-to-frame speed [m/s] of one link_poses (T, L, 7) column's position."""
    p = np.asarray(link_poses, np.float64)[:, column, :3]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).max(initial=0.0) / dt)


def cut_actions(task: Any, actions: np.ndarray, frames: int, case: str) -> np.ndarray:
    """The first `frames` actions; a hand-off must still release inside them (with >= 2 frames after)."""
    if task.handoff:
        release = release_frame(task, actions)
        if release + 2 > frames:
            raise ParamsError(f"stress.rollout_frames ({frames - 1}) ends before case {case!r} ({task.name}) "
                              f"releases its held object at frame {release}; raise rollout_frames")
    return actions[:frames]


def simulate_case(params: dict[str, Any], cfg: StressConfig, name: str, index: int) -> dict[str, Any]:
    """Episodes of one case: {"episodes": [dict of arrays + attrs], "attempts": [verdicts], "wall_s"}."""
    started = time.perf_counter()
    p = case_params(params, cfg, name)
    scene_cfg = load_section(p, "scene", SceneConfig)
    sim_cfg = replace(load_section(p, "sim", SimConfig), worlds=1)
    validate_cfg = load_section(p, "validate", ValidateConfig)
    task = get_task(cfg.case_task(name), p)
    world = build_task_world(scene_cfg, sim_cfg, task)
    planner = CoveragePlanner()
    kept, attempts = [], []
    for attempt in range(cfg.max_attempts):
        if len(kept) == cfg.episodes:
            break
        spec = planner.propose(task, episode_seed(cfg.seed, index, attempt))
        runnable, _ = reset_batch(world, [spec])
        if not runnable:
            planner.record(spec, UNREACHABLE)
            attempts.append(UNREACHABLE)
            continue
        _, state, actions = runnable[0]
        actions = cut_actions(task, actions, cfg.rollout_frames + 1, name)
        results, actions, release = execute(world, [state], [actions], None)
        (x, v), action = results[0], actions[0]
        poses = world.scene.link_poses(action)
        failure = judge(world, spec, x, v, action, poses, validate_cfg, sim_cfg.frame_dt_s)
        verdict, frame = failure if failure else (None, None)
        planner.record(spec, verdict, frame)
        attempts.append(verdict or "accepted")
        if verdict in INSANE:
            continue
        column = list(world.scene.link_names).index(TCP_LINK)
        kept.append({
            "arrays": (x, v, action, poses, np.repeat(world.scene.env_poses()[None], len(action), axis=0)),
            "attrs": {"task": task.name, "seed": spec.seed, "cell": spec.cell, "speed": spec.speed,
                      "amplitude": spec.amplitude, "split": "test", "accepted": verdict is None,
                      "first_failure": verdict, "failure_frame": frame, "source": "simulator", "case": name,
                      "overrides": {**cfg.overrides, **cfg.cases[name].overrides},
                      "peak_tcp_speed_m_s": peak_speed_m_s(poses, column, sim_cfg.frame_dt_s),
                      **layout_attrs(world, release)},
        })
    if not kept:
        raise RuntimeError(f"stress case {name!r} ({task.name}): no physically sane episode in "
                           f"{cfg.max_attempts} attempts (verdicts: {attempts}); raise stress.max_attempts or "
                           "soften the case's overrides")
    return {"episodes": kept, "attempts": attempts, "wall_s": time.perf_counter() - started,
            "solver_steps": world.solver_steps}


def case_results(params: dict[str, Any], cfg: StressConfig) -> Iterator[dict[str, Any]]:
    """simulate_case of every case, in case order; stress.workers > 1: in that many spawned processes."""
    names = list(cfg.cases)
    with tqdm(total=len(names), desc="stress ground truth", unit="case") as bar:
        if cfg.workers == 1:
            for index, name in enumerate(names):
                yield simulate_case(params, cfg, name, index)
                bar.update()
            return
        with spawn_pool(min(cfg.workers, len(names)), init_worker, (torch.get_num_threads(),)) as pool:
            futures = [pool.submit(simulate_case, params, cfg, name, i) for i, name in enumerate(names)]
            for future in futures:
                yield future.result()
                bar.update()


def stored_truth(path: Path, phash: str) -> TrajectoryStore | None:
    """The store at `path` if it was written for exactly this params hash, else None."""
    if not (path / "zarr.json").is_file():
        return None
    store = TrajectoryStore(path)
    return store if store.attrs.get("params_hash") == phash else None


def ground_truth(params: dict[str, Any], cfg: StressConfig, path: str | Path) -> tuple[TrajectoryStore, dict[str, Any]]:
    """The stress store at `path` (simulated and written atomically unless a matching one is there) and a
    report: per case its episodes, attempts' verdicts and simulation wall time."""
    path = Path(path)
    phash = truth_hash(params, cfg)
    store = stored_truth(path, phash)
    if store is not None:
        return store, {"reused": True, "store": str(path), "params_hash": phash}
    scene_cfg = load_section(params, "scene", SceneConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    tasks = [get_task(cfg.case_task(n), params) for n in cfg.cases]
    cases: dict[str, Any] = {}
    started = time.perf_counter()
    with simulator_store(path, scene_cfg, sim_cfg, tasks, phash, "stages.stress") as (writer, _):
        for name, result in zip(cfg.cases, case_results(params, cfg)):
            ids = [writer.add_episode(*e["arrays"], **e["attrs"]) for e in result["episodes"]]
            cases[name] = {"task": cfg.case_task(name), "episodes": ids, "attempts": result["attempts"],
                           "wall_s": result["wall_s"], "solver_steps": result["solver_steps"],
                           "frames": [len(e["arrays"][0]) for e in result["episodes"]]}
    wall = time.perf_counter() - started
    return TrajectoryStore(path), {"reused": False, "store": str(path), "params_hash": phash, "wall_s": wall,
                                   "device": NewtonSimulator.device_name(sim_cfg), "cases": cases}
