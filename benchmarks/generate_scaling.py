"""Data generation on K devices of one host: simulate and expand episodes/min and speedup per K.

    python -m benchmarks.generate_scaling --tag h200x2 [--devices 1,2] [--episodes 16] [--task lift_handle]
        [--store data/source/trajectories.zarr] [--model models/worldcontact] [--params params.yaml]
        [--set KEY=VALUE ...] [--out-dir reports/gpu]
    -> <out-dir>/generate_scaling_<tag>.json (+ .md), a row per K and stage with gpus, stage, episodes, accepted,
       wall_s, episodes_per_min, speedup

For each K, from the same inputs: the simulate stage (task --task, exactly --episodes episodes simulated: as many
attempts allowed as accepted episodes wanted, so the work does not hang on the acceptance rate and whole batches of
sim.worlds are proposed at once; `agent.executor: processes` on K device processes, max(K) x --in-flight batches in
flight for every K) and the expand stage (--episodes generated episodes wanted from --store's accepted episodes of
expand.task with --model, expand.shards = max(K), placed on K device processes). Both do the same work for every K
(the stores depend on batches_in_flight and shards, not on K), so speedup = episodes/min(K) / episodes/min(1) of the
same stage, measured in this run; --repeat-first runs the first K twice, a control for the store comparison (the
stages' own run-to-run repeatability). Wall times include starting the device processes (warp kernels from the cache).
Without GPUs the K processes run on the CPU: the same code path, a smoke check, not a speed.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from wc.agent import simulate_stage
from wc.config import load_section, read_params
from wc.data.store import TrajectoryStore
from wc.distributed.processes import visible_gpus
from wc.expand import ExpandConfig, expand
from wc.paths import EXPAND
from wc.reports import host_environment, write_report_atomic


def stage_params(args: argparse.Namespace, k: int, ks: list[int]) -> dict[str, Any]:
    """The params of K devices: the same work for every K, placed on K device processes."""
    overrides = [f"agent.tasks=[{args.task}]", f"agent.episodes_per_task={args.episodes}",
                 f"agent.max_attempts_per_task={args.episodes}", "agent.workers=1", "agent.executor=processes",
                 f"agent.batches_in_flight={max(ks) * args.in_flight}", f"expand.shards={max(ks)}",
                 "expand.executor=local", f"processes.devices={k}", *args.overrides]
    params = read_params(args.params, overrides)
    cfg = load_section(params, "expand", ExpandConfig)
    sources = TrajectoryStore(args.store).episodes_where(task=cfg.task, accepted=True)[:cfg.max_sources or None]
    params["expand"].update(target_trajectories=len(sources) + args.episodes,
                            max_attempts=max(cfg.max_attempts, 4 * args.episodes, max(ks)))
    return params


def timed_row(k: int, stage: str, run: Any) -> dict[str, Any]:
    """One stage run on K devices: its episodes (simulated or generated), accepted ones and wall time."""
    started = time.perf_counter()
    report = run()
    wall = time.perf_counter() - started
    episodes = report["episodes"] if stage == "simulate" else report["generated"]
    return {"gpus": k, "stage": stage, "episodes": episodes, "accepted": report["accepted"], "wall_s": wall,
            "episodes_per_min": 60.0 * episodes / wall, "executor": report["executor"],
            "stage_wall_s": report.get("wall_s"),  # wall_s less this: imports and the stage's set-up in this process
            "shards": [{k: s.get(k) for k in ("shard", "gpu", "wall_s", "timing")} for s in report.get("shards", [])]}


def store_agreement(a: Path, b: Path) -> dict[str, Any]:
    """How far store `b` is from store `a` (the same stage on 1 device): whether they hold the same episodes with the
    same verdicts, how many of those are bit-identical, and the largest position difference [m]."""
    sa, sb = TrajectoryStore(a), TrajectoryStore(b)
    same_ids = sa.episode_ids == sb.episode_ids
    verdicts = same_ids and all(sa.episode_attrs(e).get("first_failure") == sb.episode_attrs(e).get("first_failure")
                                for e in sa.episode_ids)
    identical, worst = 0, 0.0
    for eid in sa.episode_ids if same_ids else []:
        xa, xb = sa.read_episode(eid, ["x"])["x"], sb.read_episode(eid, ["x"])["x"]
        if xa.shape != xb.shape:
            worst = float("inf")
            continue
        identical += bool(np.array_equal(xa, xb))
        worst = max(worst, float(np.abs(xa - xb).max()) if xa.size else 0.0)
    return {"same_episodes": same_ids, "same_verdicts": verdicts, "identical_episodes": identical,
            "episodes": len(sa.episode_ids), "max_position_diff_m": worst if same_ids else None}


def with_speedups(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each row with its speedup: episodes/min over that of the same stage's first run on 1 device (None: none)."""
    base: dict[str, float] = {}
    for r in rows:
        if r["gpus"] == 1:
            base.setdefault(r["stage"], r["episodes_per_min"])
    return [{**r, "speedup": r["episodes_per_min"] / base[r["stage"]] if base.get(r["stage"]) else None}
            for r in rows]


def markdown(report: dict[str, Any]) -> str:
    env = report["environment"]
    lines = [f"# Data generation scaling ({report['tag']})", "",
             f"{env.get('gpu', report['device'])}, torch {env['torch']}, warp {env['warp']}, newton {env['newton']}; "
             f"{report['episodes']} episodes wanted per stage and K (simulate {report['task']}, expand "
             f"{report['expand_task']} in {report['shards']} shards)."
             + ("" if report["device"].startswith("cuda") else " CPU processes: a smoke run, not a speed."), "",
             "| gpus | stage | episodes | accepted | wall s | episodes/min | speedup | store vs the first K |",
             "|---" * 8 + "|"]
    for r in report["rows"]:
        speedup = f"{r['speedup']:.2f}" if r["speedup"] is not None else "-"
        same = r.get("same_as_first")
        agree = ("-" if same is None else f"{same['identical_episodes']}/{same['episodes']} identical, verdicts "
                 f"{'equal' if same['same_verdicts'] else 'differ'}, max {same['max_position_diff_m']} m")
        gpus = f"{r['gpus']} (repeat)" if r.get("repeat") else r["gpus"]
        lines.append(f"| {gpus} | {r['stage']} | {r['episodes']} | {r['accepted']} | {r['wall_s']:.1f} | "
                     f"{r['episodes_per_min']:.2f} | {speedup} | {agree} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--store", default=EXPAND["store"], help="validated source store (expand's input)")
    parser.add_argument("--model", default=EXPAND["model"], help="world model folder (expand's input)")
    parser.add_argument("--devices", default=None, help="comma-separated K (default 1, 2, 4, 8 up to the GPUs; 1, 2 "
                                                        "without GPUs)")
    parser.add_argument("--task", default="lift_handle", help="task program simulated")
    parser.add_argument("--episodes", type=int, default=16, help="episodes simulated (simulate), accepted generated "
                                                                 "episodes wanted (expand)")
    parser.add_argument("--in-flight", type=int, default=2, help="batches in flight per device at the largest K")
    parser.add_argument("--repeat-first", action="store_true",
                        help="run the first K twice: the second run's stores against the first show whether the "
                             "stages repeat themselves (on CUDA: see WC_DETERMINISTIC, wc/determinism.py)")
    parser.add_argument("--tag", default="cpu")
    parser.add_argument("--out-dir", default="reports/gpu")
    args = parser.parse_args(argv)
    gpus = len(visible_gpus())
    ks = ([int(k) for k in args.devices.split(",")] if args.devices
          else [k for k in (1, 2, 4, 8) if k <= max(gpus, 2)])
    if gpus and max(ks) > gpus:
        raise SystemExit(f"generate_scaling: asked for {max(ks)} devices, the machine has {gpus} GPUs")
    device = "cuda" if gpus else "cpu"
    work = Path(tempfile.mkdtemp(prefix="generate_scaling_"))
    first = stage_params(args, 1, ks)
    report: dict[str, Any] = {"tag": args.tag, "device": device, "task": args.task, "episodes": args.episodes,
                              "expand_task": first["expand"]["task"], "shards": max(ks), "store": args.store,
                              "model": args.model, "overrides": args.overrides, "environment": host_environment(device, gpus),
                              "rows": []}
    out = Path(args.out_dir) / f"generate_scaling_{args.tag}.json"
    runs = [(k, False) for k in ks]
    if args.repeat_first:
        runs.insert(1, (ks[0], True))
    for k, repeat in runs:
        params, d = stage_params(args, k, ks), work / (f"k{k}_repeat" if repeat else f"k{k}")
        rows = [timed_row(k, "simulate", lambda: simulate_stage.run(params, d / "raw.zarr", d / "simulate.json",
                                                                      memory=None)),
                timed_row(k, "expand", lambda: expand(params, args.model, args.store, d / "expanded.zarr",
                                                      d / "expand.json"))]
        if repeat or k != ks[0]:  # the same work again, or placed on other devices: the same stores?
            for row, name in zip(rows, ("raw.zarr", "expanded.zarr")):
                row["same_as_first"] = store_agreement(work / f"k{ks[0]}" / name, d / name)
                row["repeat"] = repeat
        report["rows"] = with_speedups(report["rows"] + rows)
        write_report_atomic(out, report, markdown(report))
        print(markdown(report), flush=True)
    return report


if __name__ == "__main__":
    main()
