"""Issue 24's benchmark: episodes per minute of the simulate stage with the ray executor, 1 worker vs N workers
sharing one GPU (or the CPU), each worker simulating `sim.worlds` Newton worlds per batch; the local executor in
this process as the reference row.

Every row runs the stage's own `simulate` on the same task from the same seed and an empty failure memory, until
`--minutes` of wall time have passed (no batch starts after that; what runs finishes). Ray rows run on one Ray
instance this script starts, with `agent.batches_in_flight` = N batches of the task in flight and
`ray.gpus_per_unit` = 1/N on cuda (N at once on one GPU), `ray.cpus_per_unit` 1. A warm-up (`--warm-up-minutes`,
a local row and a ray row of the most workers, not recorded) first starts the worker processes, imports, loads the
kernels and builds each worker's world, so the rows compare steady throughput, as on a running cluster; with
`--warm-up-minutes 0` each row pays those costs (cold). Writes the rows as JSON and a Markdown table beside it.

    python scripts/gpu/issue24_bench.py --device cuda --workers 1 4 8 --worlds 8 --minutes 1.5 \
        --out reports/gpu/simulate_ray_h100.json [--set key=value ...]
"""

from __future__ import annotations

import argparse
import subprocess
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import ray
import torch

from wc.agent.simulate_stage import simulate
from wc.config import add_params_arguments, read_params
from wc.reports import environment_info, write_atomic, write_json_atomic


def bench_params(args: argparse.Namespace, executor: str, workers: int) -> dict[str, Any]:
    """The params file with the run's overrides, the row's executor and its N workers."""
    sets = [f"sim.device={args.device}", f"validate.device={args.device}", f"sim.worlds={args.worlds}",
            f"agent.tasks=[{args.task}]", "agent.episodes_per_task=100000", "agent.max_attempts_per_task=100000",
            "agent.workers=1", f"agent.executor={executor}", f"agent.batches_in_flight={workers}",
            f"ray.gpus_per_unit={1.0 / workers}", "ray.cpus_per_unit=1"]
    return read_params(args.params, sets + args.overrides)


def run_row(args: argparse.Namespace, executor: str, workers: int, folder: Path, minutes: float) -> dict[str, Any]:
    """One row: the stage's report, cut to what the table needs."""
    torch.set_num_threads(1)  # as stages.simulate runs
    started = time.perf_counter()
    name = f"{executor}{workers}-{time.monotonic_ns()}"
    r = simulate(bench_params(args, executor, workers), folder / f"{name}.zarr", folder / f"{name}.json", None, minutes)
    wall = time.perf_counter() - started
    task = r["tasks"][args.task]
    return {"executor": executor, "workers": workers, "worlds": args.worlds, "episodes": r["episodes"],
            "accepted": r["accepted"], "wall_s": round(wall, 1),
            "episodes_per_min": round(60.0 * r["episodes"] / wall, 2),
            "batch_wall_s_mean": round(task["wall_s"] / max(1, r["executor"].get("units", 1)), 2)
            if executor == "ray" else None,
            "solver_steps_per_s": round(r["solver_steps_per_s"]), "stopped_early": r["stopped_early"],
            "failures": task["failures"], "executor_report": r["executor"]}


def table(rows: list[dict[str, Any]], reference: float) -> str:
    lines = ["| executor | workers | worlds each | episodes | accepted | wall s | episodes/min | vs first row |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['executor']} | {r['workers']} | {r['worlds']} | {r['episodes']} | {r['accepted']} | "
                     f"{r['wall_s']} | {r['episodes_per_min']} | {r['episodes_per_min'] / reference:.2f}x |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--device", default="cuda", help="sim.device and validate.device (cpu, cuda)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 4, 8],
                        help="ray rows: workers sharing the device")
    parser.add_argument("--worlds", type=int, default=8, help="sim.worlds: Newton worlds per worker (a batch)")
    parser.add_argument("--task", default="lift_handle")
    parser.add_argument("--minutes", type=float, default=1.5, help="per row: no batch starts after this wall time")
    parser.add_argument("--warm-up-minutes", type=float, default=0.3, help="0: cold rows (see above)")
    parser.add_argument("--no-local", action="store_true", help="skip the local-executor reference row")
    parser.add_argument("--out", type=Path, default=Path("reports/gpu/simulate_ray.json"))
    args = parser.parse_args()
    rows = []
    plan = [("local", 1)] * (not args.no_local) + [("ray", w) for w in args.workers]
    with TemporaryDirectory() as tmp:
        if args.warm_up_minutes > 0:
            ray.init(include_dashboard=False)
            for executor, workers in [("local", 1), ("ray", max(args.workers))]:
                run_row(args, executor, workers, Path(tmp), args.warm_up_minutes)
        for executor, workers in plan:
            rows.append(run_row(args, executor, workers, Path(tmp), args.minutes))
            print(f"issue24_bench: {executor} x{workers}: {rows[-1]['episodes_per_min']} episodes/min", flush=True)
    try:  # the GPU machine's copy of the tree may have no git
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = ""
    result = {"what": "simulate episodes per minute, the ray executor with N workers sharing the device (N batches of "
                      "one task in flight) vs one; the local executor in-process as reference",
              "params": args.params, "overrides": args.overrides, "device": args.device, "task": args.task,
              "minutes_per_row": args.minutes, "warm_up_minutes": args.warm_up_minutes, "code": commit or None,
              "rows": rows,
              "environment": environment_info(args.device)}
    write_json_atomic(args.out, result)
    reference = rows[0]["episodes_per_min"] or 1.0
    where = result["environment"].get("gpu", "CPU")
    text = (f"# simulate on the ray executor: {args.task}, {args.device} ({where})\n\n"
            f"{result['what']}; {args.minutes} min per row after a {args.warm_up_minutes} min warm-up, code {commit}. "
            "Generated by scripts/gpu/issue24_bench.py."
            f"\n\n{table(rows, reference)}")
    write_atomic(args.out.with_suffix(".md"), lambda p: p.write_text(text))
    print(text)


if __name__ == "__main__":
    main()
