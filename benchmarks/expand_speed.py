"""Accepted lifts per GPU-minute: the source simulator against the world model's expansion, in one run, on one task
and scene, with the device and versions.

    python -m benchmarks.expand_speed --params params.yaml [--set key=value ...] [--task lift_handle]
        [--worlds 32,64,128] [--newton-seconds 60] [--sources 25] [--target 150] [--warmup 16] [--teacher-plans 64]
        [--model models/pretrained/worldcontact-lift-handle] [--work DIR] --out reports/gpu/expand_speed_<device>.json

1. Newton, at the params' sim settings (run it at `sim.iterations=20`, where Newton's lifts converge): for each worlds
   count, batches of proposed episodes are reset, settled, planned, simulated and judged by the source data's checks
   (what the simulate stage does per batch), after one warm-up batch, until --newton-seconds have passed: accepted
   episodes per minute, checks included. Every episode Newton simulated is kept.
2. Newton's episodes are written to a store and validated; the expansion's sources are the first --sources accepted.
3. The expand stage (the params' expand section, its engine) runs once to a small target (--warmup generated: CUDA
   graphs, kernel loads) and then to --target trajectories: accepted per minute, planning, checks and writing included.
4. The teacher check replays the first --teacher-plans generated plans (accepted and rejected) in Newton at the same
   settings: verdict agreement and the RMS distance between the two rollouts.
The ratio is WorldContact's accepted per minute over Newton's best row. Writes the .json, a .md and a .png.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.expand_speed_report import chart, markdown, speed_row
from wc.agent.planner import CoveragePlanner
from wc.agent.runner import EpisodeRecord, build_task_world, simulate_batch, simulator_store
from wc.config import add_params_arguments, load_section, read_params
from wc.data.store import TrajectoryStore
from wc.devices import resolve_warp_device
from wc.expand.stage import expand
from wc.expand.teacher import teacher_check
from wc.reports import environment_info, write_json_atomic, write_report_atomic
from wc.scene.config import SceneConfig
from wc.seeds import episode_seed
from wc.sim.config import SimConfig
from wc.tasks.base import get_task
from wc.validate.config import ValidateConfig
from wc.validate.stage import validate


def _ints(text: str) -> list[int]:
    values = [int(t) for t in text.split(",") if t.strip()]
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers separated by commas, got {text!r}")
    return values


def newton_rate(params: dict[str, Any], task_name: str, worlds: int, seconds: float, first_seed: int
                ) -> tuple[dict[str, Any], list[EpisodeRecord]]:
    """Newton's accepted episodes per minute at `worlds` worlds (one warm-up batch, then batches for >= seconds),
    and every record it simulated (warm-up included)."""
    params = copy.deepcopy(params)
    params["sim"]["worlds"] = worlds
    sim_cfg, validate_cfg = load_section(params, "sim", SimConfig), load_section(params, "validate", ValidateConfig)
    task = get_task(task_name, params)
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, task)
    planner, proposed = CoveragePlanner(), 0

    def batch() -> tuple[list[EpisodeRecord], float]:
        nonlocal proposed
        specs = [planner.propose(task, episode_seed(first_seed, 0, proposed + k)) for k in range(worlds)]
        proposed += worlds
        started = time.perf_counter()
        records = simulate_batch(world, specs, validate_cfg)
        wall = time.perf_counter() - started
        for r in records:
            planner.record(r.spec, r.first_failure, r.failure_frame)
        return records, wall

    warm, warm_s = batch()
    measured, elapsed = [], 0.0
    while elapsed < seconds:
        records, wall = batch()
        measured += records
        elapsed += wall
    accepted = sum(r.first_failure is None for r in measured)
    row = {"worlds": worlds, "episodes": len(measured), "accepted": accepted, "seconds": elapsed,
           "warmup_s": warm_s, "accepted_per_min": 60.0 * accepted / elapsed,
           "episodes_per_min": 60.0 * len(measured) / elapsed, "acceptance": accepted / max(1, len(measured)),
           "iterations": sim_cfg.iterations, "substeps": sim_cfg.substeps}
    return row, warm + measured


def write_newton_store(params: dict[str, Any], task_name: str, records: list[EpisodeRecord], path: Path) -> int:
    """Newton's storable episodes (accepted and rejected, with their verdicts) as a raw store; returns how many."""
    sim_cfg = load_section(params, "sim", SimConfig)
    task = get_task(task_name, params)
    count = 0
    with simulator_store(path, load_section(params, "scene", SceneConfig), sim_cfg, [task], "benchmark",
                         "benchmarks.expand_speed") as (writer, _):
        for r in records:
            if r.x is None:
                continue
            s = r.spec
            writer.add_episode(r.x, r.v, r.action, r.link_poses, r.env_poses, task=s.task, seed=s.seed, cell=s.cell,
                               speed=s.speed, amplitude=s.amplitude, split=None, accepted=r.first_failure is None,
                               first_failure=r.first_failure, failure_frame=r.failure_frame, source="simulator",
                               **r.layout)
            count += 1
    return count


def expansion_row(report: dict[str, Any]) -> dict[str, Any]:
    """The figures of one expand report the benchmark keeps."""
    keys = ("engine", "slots", "generated", "accepted", "acceptance_rate", "rejections", "infeasible_plans", "wall_s",
            "accepted_per_min", "frames_generated", "rollout_s", "projection_stats", "timing", "restarts",
            "tail_shrinks")
    return {k: report.get(k) for k in keys}


def run(args: argparse.Namespace) -> dict[str, Any]:
    base = read_params(args.params, args.overrides)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    out = Path(args.out)
    device = resolve_warp_device(base["sim"]["device"], "sim.device")
    report: dict[str, Any] = {
        "benchmark": "expand_speed", "task": args.task, "command": " ".join(sys.argv), "params": args.params,
        "overrides": args.overrides, "model": args.model, "environment": environment_info(device),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "newton": [], "rows": [],
        "what": "accepted episodes per minute on one device: Newton (reset, settle, plan, simulate, checks) per worlds "
                "count against the expand stage (plan, roll out, project, checks, write) from Newton's first "
                f"{args.sources} accepted episodes; teacher check on {args.teacher_plans} generated plans",
    }
    records: list[EpisodeRecord] = []
    raw, store = work / "newton_raw.zarr", work / "newton_sources.zarr"
    if args.reuse_newton:  # a run cut short after its Newton rows: they and the validated store are kept
        report["newton"] = json.loads(out.read_text())["newton"]
        report["newton_reused_from"] = str(out)
    for k, worlds in enumerate([] if args.reuse_newton else args.worlds):
        row, recs = newton_rate(base, args.task, worlds, args.newton_seconds, args.seed + 1000 * k)
        report["newton"].append(row)
        records += recs
        print(f"newton {worlds} worlds: {row['accepted_per_min']:.1f} accepted/min ({row['acceptance']:.2f})", flush=True)
        write_json_atomic(out, report)
    if not args.reuse_newton:
        write_newton_store(base, args.task, records, raw)
        validate(base, raw, store, work / "validate.json")
    params = copy.deepcopy(base)
    params["expand"].update(task=args.task, max_sources=args.sources)
    warm = copy.deepcopy(params)
    warm["expand"].update(target_trajectories=args.sources + args.warmup, max_attempts=4 * args.warmup)
    expand(warm, args.model, store, work / "warm.zarr", work / "warm.json", work / "warm_rejected.zarr")
    params["expand"].update(target_trajectories=args.target, max_attempts=4 * args.target)
    gen = expand(params, args.model, store, work / "expanded.zarr", work / "expand.json", work / "rejected.zarr")
    report["expand"] = expansion_row(gen)
    print(f"expand: {gen['accepted']}/{gen['generated']} accepted, {gen['accepted_per_min']:.1f} accepted/min",
          flush=True)
    write_json_atomic(out, report)
    teacher = teacher_check(params, work / "expanded.zarr", args.teacher_plans, work / "rejected.zarr")
    report["teacher"] = {k: teacher.get(k) for k in ("plans", "agreement", "precision", "recall", "newton_accepts",
                                                      "constant_agreement", "mean_rms_error_m",
                                                      "accepted_mean_rms_error_m", "confusion", "wall_s")}
    src = TrajectoryStore(store)
    first = src.episodes_where(task=args.task, accepted=True)[0]
    vertices = int(src.read_window(first, 0, 1, ("x",))["x"].shape[1])  # the scene's object vertices, as simulated
    report["rows"].append(speed_row(report["newton"], gen, report["teacher"]) | {"vertices": vertices})
    report["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    write_report_atomic(out, report, markdown(report))
    chart(report, out.with_suffix(".png"))
    return report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--task", default="lift_handle")
    parser.add_argument("--worlds", type=_ints, default=[32, 64, 128], help="Newton worlds per batch, e.g. 32,64,128")
    parser.add_argument("--newton-seconds", type=float, default=60.0, help="measured Newton time per worlds count")
    parser.add_argument("--sources", type=int, default=25, help="Newton's accepted episodes the expansion starts from")
    parser.add_argument("--target", type=int, default=150, help="expand.target_trajectories (sources included)")
    parser.add_argument("--warmup", type=int, default=16, help="generated episodes of the warm-up expansion")
    parser.add_argument("--teacher-plans", type=int, default=64, help="generated plans replayed in Newton")
    parser.add_argument("--model", default="models/pretrained/worldcontact-lift-handle")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", default="/tmp/expand_speed", help="folder for the stores the run makes")
    parser.add_argument("--out", default="reports/expand_speed.json")
    parser.add_argument("--reuse-newton", action="store_true",
                        help="keep the Newton rows of --out and the validated store in --work (a run cut short)")
    args = parser.parse_args(argv)
    if min(args.sources, args.target - args.sources, args.warmup, args.teacher_plans) < 1 or args.newton_seconds <= 0:
        parser.error("--sources, --warmup, --teacher-plans and --target - --sources must be >= 1, --newton-seconds > 0")
    report = run(args)
    print(markdown(report))


if __name__ == "__main__":
    main()
