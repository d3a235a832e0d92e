"""Speed of the Newton source simulator on the bag-lift scene (task lift_handle), several settings in one run.

    python -m benchmarks.sim_speed --params params.yaml [--set key=value ...] [--device auto]
        [--vertices 300,20274] [--worlds 1,4,8] [--frames 50] [--repeats 3] [--quick]
        --out reports/sim_speed_<tag>.json           (also writes reports/sim_speed_<tag>.md)

Each setting (bag vertices x worlds) runs the real episode like `stages.simulate`: scene, simulator,
settle with the robot held, the task's action program (one episode per world). Warm-up: the rollout
from the settled state up to the frame where the gripper starts closing (kernel compile, CUDA graph
capture). Timed: `--frames` frames from there (pinching and lifting), the median of `--repeats` runs
from the same state, device synchronized before each clock read. A timed run is one
`NewtonSimulator.rollout_batch` call: solver steps plus the per-frame state read-back to host memory
that data generation does; no disk I/O. Aggregate = worlds x simulated s per wall s. The reports are
rewritten after each setting, so a run cut short keeps what it measured.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp
from tqdm import tqdm

from wc.agent.planner import CoveragePlanner
from wc.agent.runner import episode_seed, pad_to_length
from wc.config import add_params_arguments, load_section, read_params
from wc.devices import resolve_warp_device
from wc.dynamics import ObjectState
from wc.reports import environment_info, write_report_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import InfeasibleEpisode, get_task

TASK = "lift_handle"
PAPER_VERTICES = 20274


def _ints(text: str) -> list[int]:
    return [int(t) for t in text.split(",") if t.strip()]


def closing_frame(actions: np.ndarray) -> int:
    """First frame whose commanded gripper opening is below frame 0's (the pinch starts)."""
    closing = np.flatnonzero(actions[:, 13] < actions[0, 13] - 1e-6)
    return int(closing[0]) if len(closing) else 0


def measure(params: dict[str, Any], frames: int, repeats: int, seed: int = 0) -> dict[str, Any]:
    """Settle, warm up and time one setting; returns its row of the report."""
    scene_cfg = load_section(params, "scene", SceneConfig)
    cfg = load_section(params, "sim", SimConfig)
    task = get_task(TASK, params)
    started = time.perf_counter()
    scene = build_scene(scene_cfg, task.objects)
    sim = NewtonSimulator(scene, cfg)
    build_s = time.perf_counter() - started
    planner = CoveragePlanner()
    specs, initial, held = [], [], []  # one feasible episode per world, drawn as the agent draws them
    for i in range(100 * sim.worlds):
        spec = planner.propose(task, episode_seed(seed, 0, i))
        try:
            x0 = task.initial_state(scene, spec, np.random.default_rng(spec.seed))
            held.append(task.settle_action(scene, spec, x0))
        except InfeasibleEpisode:
            continue
        specs.append(spec)
        initial.append(x0)
        if len(specs) == sim.worlds:
            break
    if not specs:
        raise RuntimeError(f"no feasible episode of {TASK} in {100 * sim.worlds} draws")
    settle_frames = int(round(cfg.settle_s / cfg.frame_dt_s))
    label = f"{len(scene.objects['bag'].vertices)} v x {sim.worlds} w"
    with tqdm(total=settle_frames, desc=f"{label}: settle+warm-up", unit="frame", leave=False) as bar:
        t = time.perf_counter()
        settled = sim.settle(initial, held, cfg.settle_s)
        settle_wall = time.perf_counter() - t
        bar.update(settle_frames)
        runnable = []  # an episode unplannable after settling leaves its world to repeat another (rollout_batch pads)
        for st, spec, a0 in zip(settled, specs, held):
            try:
                runnable.append((st, task.actions(scene, st, spec, a0, cfg.frame_dt_s)))
            except InfeasibleEpisode:
                pass
        if not runnable:
            raise RuntimeError(f"{label}: no episode of {TASK} could be planned after settling")
        settled, actions = [r[0] for r in runnable], [r[1] for r in runnable]
        start = max(2, min(closing_frame(a) for a in actions))  # >= 2 frames: the CUDA graph gets captured
        length = max(start + frames + 1, max(len(a) for a in actions))
        actions = [pad_to_length(a, length) for a in actions]
        bar.total += start
        t = time.perf_counter()
        warm = sim.rollout_batch(settled, [a[: start + 1] for a in actions], on_frame=lambda: bar.update())
        wp.synchronize_device(sim.device)
        warmup_wall = time.perf_counter() - t
    from_state = [ObjectState(x[-1], v[-1]) for x, v in warm]
    window = [a[start: start + frames + 1] for a in actions]
    walls, finite = [], True
    for _ in tqdm(range(repeats), desc=f"{label}: timed", unit="run", leave=False):
        steps = sim.solver_steps
        wp.synchronize_device(sim.device)
        t = time.perf_counter()
        out = sim.rollout_batch(from_state, window)
        wp.synchronize_device(sim.device)
        walls.append(time.perf_counter() - t)
        steps = sim.solver_steps - steps
        finite &= all(bool(np.isfinite(x).all() and np.isfinite(v).all()) for x, v in out)
    wall = statistics.median(walls)
    per_world = steps * cfg.dt_s / wall
    return {
        "bag_vertices": len(scene.objects["bag"].vertices), "worlds": sim.worlds,
        "particles_total": int(sim.model.particle_count), "iterations": cfg.iterations,
        "episodes": len(actions), "self_contact": cfg.self_contact, "dt_s": cfg.dt_s, "substeps": cfg.substeps,
        "timed_frames": frames, "timed_solver_steps": steps, "timed_from_frame": start,
        "repeats": repeats, "wall_s": walls, "wall_s_median": wall, "ms_per_frame": 1e3 * wall / frames,
        "solver_steps_per_s": steps / wall, "simulated_s_per_wall_s": per_world,
        "simulated_s_per_wall_s_aggregate": per_world * sim.worlds, "finite": finite,
        "build_s": build_s, "settle_wall_s": settle_wall, "warmup_wall_s": warmup_wall,
    }


def markdown(report: dict[str, Any]) -> str:
    env = report["environment"]
    lines = [f"# Source simulator speed: bag lift ({TASK})", "",
             f"Device {env['device']} ({env.get('gpu', env['cpu'])}), warp {env['warp']}, newton {env['newton']}, "
             f"torch {env['torch']}; params {report['params']} {' '.join(report['overrides'])}.",
             f"Timed: {report['frames']} frames from the gripper's closing frame, median of {report['repeats']}, "
             "rollout_batch incl. per-frame state read-back, no disk I/O.", "",
             "| bag vertices | worlds (episodes) | iterations | self-contact | steps/s | sim s / wall s (per world) "
             "| aggregate | ms/frame | wall s (median) | finite |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["settings"]:
        lines.append(f"| {r['bag_vertices']:,} | {r['worlds']} ({r['episodes']}) | {r['iterations']} | {'on' if r['self_contact'] else 'off'} "
                     f"| {r['solver_steps_per_s']:.1f} | {r['simulated_s_per_wall_s']:.3f} "
                     f"| {r['simulated_s_per_wall_s_aggregate']:.3f} | {r['ms_per_frame']:.1f} "
                     f"| {r['wall_s_median']:.2f} | {'yes' if r['finite'] else 'NO'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--device", default=None, help="cpu | cuda | cuda:N | auto (default: params' sim.device)")
    parser.add_argument("--vertices", type=_ints, default=None,
                        help=f"bag target_vertices list (default: params' and {PAPER_VERTICES}; --quick: params')")
    parser.add_argument("--worlds", type=_ints, default=None, help="world counts (default: 1,4,8 on cuda, 1 on cpu)")
    parser.add_argument("--frames", type=int, default=None, help="timed frames per run (default 50; --quick 10)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="smoke test: params' bag only, 1 world, 10 frames")
    parser.add_argument("--out", default="reports/sim_speed.json")
    args = parser.parse_args(argv)

    base = read_params(args.params, args.overrides)
    device = resolve_warp_device(args.device or base["sim"]["device"], "sim.device")
    own = base["scene"]["bag"]["target_vertices"]
    vertices = args.vertices or ([own] if args.quick else list(dict.fromkeys([own, PAPER_VERTICES])))
    worlds = args.worlds or ([1, 4, 8] if device.startswith("cuda") and not args.quick else [1])
    frames = args.frames or (10 if args.quick else 50)
    out = Path(args.out)
    report: dict[str, Any] = {
        "benchmark": "sim_speed", "task": TASK, "command": " ".join(sys.argv), "params": args.params,
        "overrides": args.overrides, "frames": frames, "repeats": args.repeats,
        "environment": environment_info(device), "settings": [],
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    settings = [(v, w) for v in vertices for w in worlds]
    for v, w in tqdm(settings, desc="sim_speed", unit="setting"):
        params = read_params(args.params, [*args.overrides, f"scene.bag.target_vertices={v}", f"sim.worlds={w}",
                                           f"sim.device={device}"])
        row = measure(params, frames, args.repeats)
        report["settings"].append(row)
        tqdm.write(f"{row['bag_vertices']:>6} vertices x {w} worlds: {row['solver_steps_per_s']:.1f} steps/s, "
                   f"{row['simulated_s_per_wall_s']:.3f} sim s/wall s per world, "
                   f"{row['simulated_s_per_wall_s_aggregate']:.3f} aggregate (walls {['%.2f' % s for s in row['wall_s']]})")
        write_report_atomic(out, report, markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
