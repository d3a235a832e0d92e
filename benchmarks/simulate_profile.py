"""Where the simulate stage's time goes: one task's batch of episodes (`run_episodes`, as stages.simulate runs it)
with a wall clock on each phase (planning + settling, settling, the rollout: solver steps, state read-back; the
acceptance checks and forward kinematics) and cProfile's top functions beside it.

    python -m benchmarks.simulate_profile [--params params.yaml] [--set sim.worlds=16 --set sim.device=cuda ...]
        [--task lift_handle] [--episodes N] --out reports/simulate_profile_<tag>.json   (+ .txt: the top functions)

A GPU run that simulates much slower than benchmarks/sim_speed.py (the solver alone) says here which host work
fills the gap. The first batch carries one-time costs (imports, kernel compiles): with --warmup, one batch runs
before the profiled one.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time
from pathlib import Path

import torch

from wc.agent.planner import CoveragePlanner
from wc.agent.runner import build_task_world, run_episodes
from wc.config import add_params_arguments, load_section, read_params
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.tasks.base import get_task
from wc.validate.config import ValidateConfig

def timed_phases() -> tuple[dict[str, float], list[tuple[object, str, object]]]:
    """Wrap the phase functions with wall clocks (module globals and methods, patched where they are looked up);
    returns the seconds per phase (filled as they run) and the originals, for `restore`."""
    import wc.agent.runner as runner
    import wc.validate.predicates as predicates
    from wc.scene.scene import Scene
    from wc.sim.newton_sim import NewtonSimulator

    targets = {"reset_batch (planning + settle)": (runner, "reset_batch"), "settle": (NewtonSimulator, "settle"),
               "rollout (execute)": (runner, "execute"), "solver steps (_substeps)": (NewtonSimulator, "_substeps"),
               "state read-back (read_state)": (NewtonSimulator, "read_state"),
               "forward kinematics (link_poses)": (Scene, "link_poses"), "checks (judge)": (runner, "judge"),
               "self-intersection check": (predicates.PREDICATES, "self_intersection")}
    seconds, originals = dict.fromkeys(targets, 0.0), []
    for phase, (owner, name) in targets.items():
        original = owner[name] if isinstance(owner, dict) else getattr(owner, name)

        def clocked(*args, _f=original, _phase=phase, **kwargs):  # noqa: ANN002, ANN003, ANN202
            t0 = time.perf_counter()
            try:
                return _f(*args, **kwargs)
            finally:
                seconds[_phase] += time.perf_counter() - t0
        _set(owner, name, clocked)
        originals.append((owner, name, original))
    return seconds, originals


def _set(owner: object, name: str, value: object) -> None:
    if isinstance(owner, dict):
        owner[name] = value
    else:
        setattr(owner, name, value)


def restore(originals: list[tuple[object, str, object]]) -> None:
    for owner, name, original in originals:
        _set(owner, name, original)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--task", default="lift_handle")
    parser.add_argument("--episodes", type=int, default=0, help="episodes profiled (default: one batch, sim.worlds)")
    parser.add_argument("--warmup", action="store_true", help="run one batch first, unprofiled")
    parser.add_argument("--out", default="reports/simulate_profile.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # as stages.simulate
    params = read_params(args.params, args.overrides)
    sim_cfg = load_section(params, "sim", SimConfig)
    task = get_task(args.task, params)
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, task)
    validate_cfg = load_section(params, "validate", ValidateConfig)
    episodes = args.episodes or sim_cfg.worlds
    if args.warmup:
        list(run_episodes(world, CoveragePlanner(), 0, sim_cfg.worlds, sim_cfg.worlds, 1, validate_cfg))
    steps_before = world.sim.solver_steps
    seconds, originals = timed_phases()
    profile = cProfile.Profile()
    started = time.perf_counter()
    profile.enable()
    records = list(run_episodes(world, CoveragePlanner(), 0, episodes, episodes, 0, validate_cfg))
    profile.disable()
    wall = time.perf_counter() - started
    restore(originals)
    text = io.StringIO()
    pstats.Stats(profile, stream=text).sort_stats("cumulative").print_stats(60)
    frames = sum(len(r.x) for r in records if r.x is not None)
    solver_steps = world.sim.solver_steps - steps_before
    report = {"task": args.task, "worlds": sim_cfg.worlds, "episodes": len(records), "wall_s": wall,
              "solver_steps": solver_steps, "solver_steps_per_s": solver_steps / wall, "frames": frames,
              "phases_s": seconds, "warmup": args.warmup, "environment": environment_info(sim_cfg.device)}
    out = Path(args.out)
    write_json_atomic(out, report)
    out.with_suffix(".txt").write_text(text.getvalue())
    print(f"{len(records)} episodes in {wall:.1f} s ({solver_steps / wall:.0f} solver steps/s); "
          + ", ".join(f"{k} {v:.1f} s" for k, v in report["phases_s"].items()))


if __name__ == "__main__":
    main()
