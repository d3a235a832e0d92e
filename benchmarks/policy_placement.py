"""Policy training schedules on one host: the arms one after another on one device, against side by side (a process
each, a GPU each where the host has several).

    python -m benchmarks.policy_placement --tag h200x2 [--data-root data/lerobot] [--params params.yaml]
        [--policy params/policy_act_gpu.yaml] [--set policy.steps=500 ...] [--out-dir reports/gpu]
    -> <out-dir>/policy_placement_<tag>.{json,md}: a row per schedule with its wall time, each arm's median s/step,
       final loss and GPU, and the speedup of side by side over one after another

Both schedules run the finetune stage (`wc.policy.finetune_stage.run`) on the same datasets with the same settings
and seed, so they differ only in placement; wall times include each process's start-up and the datasets' loading.
Without GPUs the side-by-side processes share the CPU: the same code path, a check, not a speed.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

from wc.distributed.processes import visible_gpus
from wc.paths import FINETUNE
from wc.policy.finetune_stage import run, stage_params
from wc.reports import host_environment, write_report_atomic

SCHEDULES = {"one_after_another": False, "side_by_side": True}


def schedule_row(name: str, params: dict[str, Any], data_root: Path, work: Path) -> dict[str, Any]:
    """The finetune stage under one schedule: its wall time and each arm's figures."""
    params = {**params, "policy": {**params["policy"], "side_by_side": SCHEDULES[name]}}
    started = time.perf_counter()
    report = run(params, data_root, work / name / "models", work / name / "finetune.json")
    wall = time.perf_counter() - started
    arms = {arm: {k: d[k] for k in ("episodes", "frames", "s_per_step_median", "train_s", "final_loss", "gpu")}
            for arm, d in report["datasets"].items()}
    return {"schedule": name, "wall_s": wall, "arms": arms, "params_hash": report["params_hash"]}


def with_speedups(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each row with its speedup: the one-after-another wall time over its own."""
    base = next((r["wall_s"] for r in rows if r["schedule"] == "one_after_another"), None)
    return [{**r, "speedup": base / r["wall_s"] if base else None} for r in rows]


def markdown(report: dict[str, Any]) -> str:
    env = report["environment"]
    lines = [f"# Policy training schedules ({report['tag']})", "",
             f"{env.get('gpu', report['device'])}, torch {env['torch']}; {report['policy_type']} x "
             f"{len(report['datasets'])} datasets ({', '.join(report['datasets'])}), {report['steps']} steps of "
             f"batch {report['batch_size']} each, seed {report['seed']}."
             + ("" if report["device"] == "cuda" else " CPU processes: a check, not a speed."), "",
             "| schedule | wall s | speedup | per arm: s/step (median), final loss, GPU |", "|---|---|---|---|"]
    for r in report["rows"]:
        arms = "; ".join(f"{a}: {d['s_per_step_median']:.3f}, {d['final_loss']:.4g}, {d['gpu'] or 'shared'}"
                         for a, d in r["arms"].items())
        lines.append(f"| {r['schedule']} | {r['wall_s']:.1f} | {r['speedup']:.2f} | {arms} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--policy", default=None, help="a file whose `policy` section replaces params' own")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--data-root", default=FINETUNE["data_root"], help="the LeRobot datasets' folder")
    parser.add_argument("--schedules", default=",".join(SCHEDULES), help="comma-separated, of " + ", ".join(SCHEDULES))
    parser.add_argument("--tag", default="cpu")
    parser.add_argument("--out-dir", default="reports/gpu")
    args = parser.parse_args(argv)
    names = [s.strip() for s in args.schedules.split(",") if s.strip()]
    unknown = [s for s in names if s not in SCHEDULES]
    if unknown or not names:
        raise SystemExit(f"policy_placement: unknown schedule(s) {unknown or names}; choose from {list(SCHEDULES)}")
    params = stage_params(args.params, args.overrides, args.policy)
    policy = params["policy"]
    device = "cuda" if policy.get("device", "cpu").startswith("cuda") and visible_gpus() else "cpu"
    report: dict[str, Any] = {
        "tag": args.tag, "device": device, "gpus": len(visible_gpus()), "policy_type": policy["type"],
        "datasets": list(policy["datasets"]), "steps": policy["steps"], "batch_size": policy["batch_size"],
        "seed": policy["seed"], "data_root": args.data_root, "overrides": args.overrides,
        "environment": host_environment(device, len(visible_gpus()) if device == "cuda" else 0), "rows": []}
    out = Path(args.out_dir) / f"policy_placement_{args.tag}.json"
    work = Path(tempfile.mkdtemp(prefix="policy_placement_"))
    for name in names:
        report["rows"] = with_speedups(report["rows"] + [schedule_row(name, params, Path(args.data_root), work)])
        write_report_atomic(out, report, markdown(report))
        print(markdown(report), flush=True)
    return report


if __name__ == "__main__":
    main()
