"""A training study: several `train` settings side by side, each a `stages.train` subprocess, in parallel.

    python -m benchmarks.train_sweep --sweep benchmarks/train_sweep.yaml [--jobs 8 --threads 2] --out DIR

The sweep file maps a name to a list of `--set` overrides of params.yaml (e.g. `train.base.steps=600`).
Each run writes DIR/<name>/{model,train.json,loss.csv,log}; the summary (final validation loss against
the zero-motion and constant-velocity references, held-out rollout MSE, s/step) goes to
DIR/train_sweep.{json,md}. Runs are independent, so their order and parallelism do not change results.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import yaml

from wc.reports import environment_info, write_json_atomic

SUMMARY_KEYS = ("best_val_loss", "zero_motion_val_loss", "constant_velocity_val_loss", "rollout_position_mse_m2",
                "rollout_zero_motion_mse_m2", "s_per_step_median", "wall_s")


def run_one(name: str, overrides: list[str], params: str, store: str, out: Path, threads: int) -> dict[str, Any]:
    """Train one setting in a subprocess; its report (or the error tail) as a dict."""
    run_dir = out / name
    run_dir.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "stages.train", "--params", params, "--store", store,
           "--out", str(run_dir / "model"), "--report", str(run_dir / "train.json"),
           "--curves", str(run_dir / "loss.csv")]
    for o in overrides:
        cmd += ["--set", o]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "TQDM_MININTERVAL": "60"}
    t0 = time.perf_counter()
    with open(run_dir / "log", "w") as log:
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env=env).returncode
    if rc != 0:
        return {"name": name, "overrides": overrides, "error": (run_dir / "log").read_text()[-800:]}
    report = json.loads((run_dir / "train.json").read_text())
    return {"name": name, "overrides": overrides, "seconds": time.perf_counter() - t0,
            **{k: report.get(k) for k in SUMMARY_KEYS}}


def markdown(rows: list[dict[str, Any]]) -> str:
    """A table: one row per setting, losses relative to the zero-motion reference."""
    lines = ["| setting | overrides | val loss | zero motion | const. velocity | val / zero | rollout MSE m² | s/step |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['name']} | {' '.join(r['overrides'])} | failed | | | | | |")
            continue
        lines.append(f"| {r['name']} | {' '.join(r['overrides'])} | {r['best_val_loss']:.4g} | "
                     f"{r['zero_motion_val_loss']:.4g} | {r['constant_velocity_val_loss']:.4g} | "
                     f"{r['best_val_loss'] / r['zero_motion_val_loss']:.3f} | {r['rollout_position_mse_m2']:.3g} | "
                     f"{r['s_per_step_median']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sweep", required=True, help="YAML: name -> list of key=value overrides")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--out", default="reports/train_sweep")
    parser.add_argument("--jobs", type=int, default=max(1, (os.cpu_count() or 2) // 2))
    parser.add_argument("--threads", type=int, default=2, help="OMP threads per run")
    args = parser.parse_args(argv)
    sweep = yaml.safe_load(Path(args.sweep).read_text())
    if not isinstance(sweep, dict) or not all(isinstance(v, list) for v in sweep.values()):
        raise SystemExit(f"{args.sweep}: expected a mapping name -> list of key=value overrides")
    out = Path(args.out)
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda kv: run_one(kv[0], kv[1], args.params, args.store, out, args.threads),
                             sweep.items()))
    write_json_atomic(out / "train_sweep.json", {"runs": rows, "environment": environment_info("cpu"),
                                                 "jobs": args.jobs, "threads_per_run": args.threads})
    (out / "train_sweep.md").write_text(markdown(rows))
    print(markdown(rows))


if __name__ == "__main__":
    main()
