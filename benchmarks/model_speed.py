"""WorldContact speed on the bag-lift scene: time per optimisation step (W = 5, 10, 15, with and without
hierarchical compression) and rollout speed, beside the Newton source simulator on the same episode.

    python -m benchmarks.model_speed --params params/gpu.yaml [--windows 5,10,15] [--steps 5]
        [--rollout-frames 25] [--batch 8] --out reports/model_speed_<tag>.json   (+ .md)

1. Newton runs one lift_handle episode (the agent's first feasible draw: settle, approach, pinch,
   lift) and the wall time of its rollout gives the simulator's simulated seconds per wall second.
   The episode goes to a temporary trajectory store.
2. Per (W, compression): AdamW steps on windows of that episode, the same code as the train stage
   (`wc.train.loop.optimisation_step`, bf16 autocast as params say); median of `--steps` after 2
   warm-up steps; peak GPU memory.
3. Rollout: the trained-architecture model (random weights: speed does not depend on them) rolls
   out `--rollout-frames` frames without gradients, for 1 scene and for `--batch` scenes at once; and once more
   through the `wc.dynamics.Dynamics` protocol the Newton row is timed through (`LearnedDynamics.rollout_batch`:
   numpy states and actions in, the recorded poses, a finite check per frame, (x, v) out), so the two rows of
   `rollout_protocol` compare Newton and WorldContact through one call and show the protocol's own cost.
Device synchronised before every clock read; no disk I/O or rendering inside the timed parts.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import warp as wp

from wc.agent.planner import CoveragePlanner
from wc.agent.runner import episode_seed
from wc.config import add_params_arguments, load_section, read_params
from wc.data.store import TrajectoryStore, TrajectoryWriter
from wc.dynamics import ObjectState
from wc.model.predictor import WorldContactPredictor
from wc.model.config import ModelConfig
from wc.model.learned_dynamics import LearnedDynamics
from wc.model.prescribed_inputs import RecordedInputs
from wc.model.layout import SceneLayout, scene_layout
from wc.model.rollout import rollout
from wc.model.worldcontact import WorldContact
from wc.reports import environment_info, write_json_atomic, write_report_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import InfeasibleEpisode, get_task
from wc.train.config import TrainConfig
from wc.train.data import Phase, data_scales, episode_phases, read_phase_window
from wc.train.loop import SegmentRollout, optimisation_step

TASK = "lift_handle"


def simulate_episode(params: dict[str, Any], path: Path, seed: int = 0) -> dict[str, Any]:
    """One lift_handle episode from Newton into a store at `path`; returns the simulator's timing."""
    scene_cfg, sim_cfg = load_section(params, "scene", SceneConfig), load_section(params, "sim", SimConfig)
    sim_cfg = replace(sim_cfg, worlds=1)
    task = get_task(TASK, params)
    scene = build_scene(scene_cfg, task.objects)
    sim = NewtonSimulator(scene, sim_cfg)
    planner = CoveragePlanner()
    for i in range(100):
        spec = planner.propose(task, episode_seed(seed, 0, i))
        try:
            x0 = task.initial_state(scene, spec, np.random.default_rng(spec.seed))
            hold = task.settle_action(scene, spec, x0)
            settled = sim.settle([x0], [hold], sim_cfg.settle_s)[0]
            actions = task.actions(scene, settled, spec, hold, sim_cfg.frame_dt_s)
            break
        except InfeasibleEpisode:
            continue
    else:
        raise RuntimeError(f"no feasible {TASK} episode in 100 draws")
    sim.rollout_batch([settled], [actions[:3]])  # warm-up: kernel compile, graph capture
    wp.synchronize_device(sim.device)
    t = time.perf_counter()
    x, v = sim.rollout_batch([settled], [actions])[0]
    wp.synchronize_device(sim.device)
    wall = time.perf_counter() - t
    with TrajectoryWriter(path, dt=sim_cfg.frame_dt_s, substeps=sim_cfg.substeps, params_hash="benchmark",
                          created_by="benchmarks.model_speed", object_order=list(scene.objects),
                          link_names=list(scene.link_names), env_names=list(scene.env_names)) as w:
        w.add_scene(scene)
        w.add_episode(x, v, actions, scene.link_poses(actions), np.repeat(scene.env_poses()[None], len(actions), 0),
                      task=TASK, seed=spec.seed, cell=spec.cell, speed=spec.speed, amplitude=spec.amplitude,
                      split="train", accepted=True, first_failure=None, source="simulator")
    frames = len(actions) - 1
    return {"bag_vertices": int(x.shape[1]), "frames": frames, "wall_s": wall, "iterations": sim_cfg.iterations,
            "simulated_s_per_wall_s": frames * sim_cfg.frame_dt_s / wall, "finite": bool(np.isfinite(x).all())}


def sync(device: torch.device) -> None:
    """Wait for the device (CUDA) before a clock read; no-op on CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def episode_model(store: TrajectoryStore, model_cfg: ModelConfig, device: torch.device,
                  episode: str | None = None) -> tuple[Phase, WorldContact, SceneLayout]:
    """The benchmark episode's (default: the first) first phase, a model scaled to it, and its layout, on `device`."""
    phase = episode_phases(store, episode or store.episode_ids[0])[0]
    scales = data_scales(store, [phase], 1)
    model = WorldContact(model_cfg, scales.velocity_m_s, scales.delta_x_m, scales.delta_v_m_s).to(device)
    return phase, model, scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), model_cfg.tag_scale).to(device)


def time_training(store: TrajectoryStore, model_cfg: ModelConfig, cfg: TrainConfig, window: int, steps: int,
                  device: torch.device) -> dict[str, Any]:
    """Median seconds per optimisation step on W-frame windows of the stored episode."""
    phase, model, layout = episode_model(store, model_cfg, device)
    model.train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-5, betas=cfg.betas, weight_decay=cfg.weight_decay)
    runner = SegmentRollout(model)
    starts = np.linspace(0, phase.stop - window, steps + 2).astype(int)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    walls, losses = [], []
    for k, s in enumerate(starts):
        a = {n: torch.from_numpy(arr)[None].to(device) for n, arr in read_phase_window(store, phase, s, window).items()}
        sync(device)
        t = time.perf_counter()
        losses.append(optimisation_step(runner, optimizer, layout, a["x"], a["v"], a["poses"], store.dt, None, cfg))
        if k >= 2:  # the first two steps compile / allocate
            walls.append(time.perf_counter() - t)
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")
    return {"window": window, "compress": model_cfg.compress, "s_per_step_median": statistics.median(walls),
            "s_per_step": walls, "peak_memory_gib": peak, "finite_loss": bool(np.isfinite(losses).all())}


@torch.no_grad()
def time_rollout(store: TrajectoryStore, model_cfg: ModelConfig, frames: int, batch: int, autocast: bool,
                 device: torch.device) -> dict[str, Any]:
    """Simulated seconds per wall second of a `frames`-frame rollout of `batch` copies of the episode."""
    phase, model, layout = episode_model(store, model_cfg, device)
    model.eval()
    frames = min(frames, phase.stop - 1)
    a = {n: torch.from_numpy(arr).to(device) for n, arr in read_phase_window(store, phase, 0, frames + 1).items()}
    x0 = a["x"][0].expand(batch, -1, -1).contiguous()
    v0 = a["v"][0].expand(batch, -1, -1).contiguous()
    poses = a["poses"][None].expand(batch, -1, -1, -1).contiguous()
    walls = []
    for k in range(3):
        sync(device)
        t = time.perf_counter()
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=autocast and device.type == "cuda"):
            xs, _ = rollout(model, layout, x0, v0, poses, store.dt)
        sync(device)
        if k:
            walls.append(time.perf_counter() - t)
    wall = statistics.median(walls)
    return {"batch": batch, "frames": frames, "compress": model_cfg.compress, "autocast_bf16": autocast,
            "wall_s_median": wall, "simulated_s_per_wall_s": frames * store.dt / wall,
            "simulated_s_per_wall_s_aggregate": batch * frames * store.dt / wall,
            "finite": bool(torch.isfinite(xs).all())}


@torch.no_grad()
def time_protocol_rollout(store: TrajectoryStore, model_cfg: ModelConfig, cfg: TrainConfig, frames: int, batch: int,
                          device: torch.device) -> dict[str, Any]:
    """As `time_rollout` (fp32), through `LearnedDynamics.rollout_batch`: the call Newton's row is timed through."""
    phase, model, layout = episode_model(store, model_cfg, device)
    frames = min(frames, phase.stop - 1)
    a = read_phase_window(store, phase, 0, frames + 1)
    actions = store.read_episode(phase.episode, ("action",))["action"][phase.start:phase.start + frames + 1]
    dynamics = LearnedDynamics(WorldContactPredictor(model, False, cfg), layout,
                               RecordedInputs(actions, a["poses"], layout.bodies), store.dt, device)
    initial = [ObjectState(a["x"][0], a["v"][0])] * batch
    walls = []
    for k in range(3):
        sync(device)
        t = time.perf_counter()
        out = dynamics.rollout_batch(initial, [actions] * batch)
        sync(device)
        if k:
            walls.append(time.perf_counter() - t)
    wall = statistics.median(walls)
    return {"batch": batch, "frames": frames, "compress": model_cfg.compress, "autocast_bf16": False,
            "call": "Dynamics.rollout_batch", "wall_s_median": wall, "simulated_s_per_wall_s": frames * store.dt / wall,
            "simulated_s_per_wall_s_aggregate": batch * frames * store.dt / wall,
            "finite": bool(all(np.isfinite(x).all() for x, _ in out))}


def markdown(report: dict[str, Any]) -> str:
    env, sim = report["environment"], report["simulator"]
    lines = [f"# WorldContact speed: bag lift at {sim['bag_vertices']:,} bag vertices", "",
             f"Device {env['device']} ({env.get('gpu', env['cpu'])}), torch {env['torch']}, warp {env['warp']}, "
             f"newton {env['newton']}; params {report['params']}.", "",
             f"Newton source simulator ({sim['iterations']} iterations), same episode: "
             f"{sim['simulated_s_per_wall_s']:.3f} simulated s per wall s ({sim['frames']} frames in {sim['wall_s']:.1f} s).",
             "", "## Time per optimisation step (paper, one H100: 4.184 / 10.526 / 14.493 s with compression, "
             "4.367 / 11.236 / 15.873 s without)", "",
             "| W | hierarchical compression | s per step (median) | peak GPU memory GiB |", "|---|---|---|---|"]
    for r in report["training"]:
        if "out_of_memory" in r:
            lines.append(f"| {r['window']} | {'yes' if r['compress'] else 'no'} | out of GPU memory | - |")
            continue
        lines.append(f"| {r['window']} | {'yes' if r['compress'] else 'no'} | {r['s_per_step_median']:.3f} | "
                     f"{r['peak_memory_gib']:.1f} |")
    lines += ["", "## Rollout (no gradients)", "",
              "| scenes | compression | bf16 | simulated s / wall s per scene | aggregate | x simulator |",
              "|---|---|---|---|---|---|"]
    for r in report["rollout"]:
        lines.append(f"| {r['batch']} | {'yes' if r['compress'] else 'no'} | {'yes' if r['autocast_bf16'] else 'no'} | "
                     f"{r['simulated_s_per_wall_s']:.3f} | {r['simulated_s_per_wall_s_aggregate']:.3f} | "
                     f"{r['simulated_s_per_wall_s_aggregate'] / sim['simulated_s_per_wall_s']:.1f} |")
    lines += ["", "## Through the Dynamics protocol (Newton's row above is timed through the same call; fp32)", "",
              "| scenes | compression | simulated s / wall s per scene | aggregate | x simulator |", "|---|---|---|---|---|"]
    for r in report.get("rollout_protocol", []):
        lines.append(f"| {r['batch']} | {'yes' if r['compress'] else 'no'} | {r['simulated_s_per_wall_s']:.3f} | "
                     f"{r['simulated_s_per_wall_s_aggregate']:.3f} | "
                     f"{r['simulated_s_per_wall_s_aggregate'] / sim['simulated_s_per_wall_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--windows", default="5,10,15")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--rollout-frames", type=int, default=25)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--episode", default=None,
                        help="keep the simulated episode's store here (e.g. for benchmarks.rollout_profile)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    params = read_params(args.params, args.overrides)
    model_cfg, cfg = load_section(params, "model", ModelConfig), load_section(params, "train", TrainConfig)
    device = torch.device(cfg.device)
    out = Path(args.out)
    report: dict[str, Any] = {"params": args.params, "environment": environment_info(str(device)), "training": [],
                              "rollout": [], "rollout_protocol": []}
    with tempfile.TemporaryDirectory() as tmp:
        episode = Path(args.episode) if args.episode else Path(tmp) / "episode.zarr"
        report["simulator"] = simulate_episode(params, episode)
        store = TrajectoryStore(episode)
        print(f"simulator: {report['simulator']['simulated_s_per_wall_s']:.3f} s/s", flush=True)
        for compress in (True, False):
            mc = replace(model_cfg, compress=compress)
            for w in (int(t) for t in args.windows.split(",")):
                try:
                    report["training"].append(time_training(store, mc, cfg, w, args.steps, device))
                except torch.OutOfMemoryError as err:  # a finding, not a crash: record it and go on
                    report["training"].append({"window": w, "compress": compress, "out_of_memory": str(err)[:200]})
                    torch.cuda.empty_cache()
                print(report["training"][-1], flush=True)
                write_json_atomic(out, report)
            for batch, autocast in ((1, False), (1, cfg.autocast_bf16), (args.batch, cfg.autocast_bf16)):
                report["rollout"].append(time_rollout(store, mc, args.rollout_frames, batch, autocast, device))
                print(report["rollout"][-1], flush=True)
                write_json_atomic(out, report)
            for batch in (1, args.batch):
                report["rollout_protocol"].append(time_protocol_rollout(store, mc, cfg, args.rollout_frames, batch, device))
                print(report["rollout_protocol"][-1], flush=True)
                write_json_atomic(out, report)
    write_report_atomic(out, report, markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
