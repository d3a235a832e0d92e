"""Stage `train_baselines`: RoboCraft, RoboCook, AdaptiGraph on data/source/trajectories.zarr
-> models/baselines/<name>/ and reports/train_baselines.json.

    python -m stages.train_baselines [--params params.yaml] [--set baselines.names=[robocook] ...]

Each baseline trains on the split and holdout rule of the `train` section (wc.baselines.train).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from wc.baselines import BASELINES
from wc.baselines.config import BaselinesConfig
from wc.baselines.train import train_baseline
from wc.cli import run_cli
from wc.config import ParamsError, add_params_arguments, load_section, params_hash, read_params
from wc.reports import environment_info, write_json_atomic
from wc.train.config import TrainConfig

SECTIONS = ["baselines", "train"]


def run(params: dict[str, Any], store: str | Path = "data/source/trajectories.zarr",
        out: str | Path = "models/baselines", report: str | Path = "reports/train_baselines.json") -> dict[str, Any]:
    """Train every baseline named in params; write out/<name>/ and the report; returns the report."""
    cfg = load_section(params, "baselines", BaselinesConfig)
    train_cfg = load_section(params, "train", TrainConfig)
    unknown = [n for n in cfg.names if n not in BASELINES]
    if unknown:
        raise ParamsError(f"{params.get('_source', '<params>')}: baselines.names: unknown {unknown} "
                          f"(known: {sorted(BASELINES)})")
    if not Path(store).exists():
        raise FileNotFoundError(f"train_baselines: trajectory store not found: {store} (run the validate stage first)")
    start = time.perf_counter()
    digest = params_hash(params, SECTIONS)
    results = {name: train_baseline(name, store, Path(out) / name, cfg, train_cfg, {"params_hash": digest})
               for name in cfg.names}
    result = {"baselines": results, "wall_s": time.perf_counter() - start, "params_hash": digest,
              "environment": environment_info(cfg.device), "models": str(out)}
    write_json_atomic(report, result)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--out", default="models/baselines")
    parser.add_argument("--report", default="reports/train_baselines.json")
    args = parser.parse_args(argv)
    r = run(read_params(args.params, args.overrides), args.store, args.out, args.report)
    for name, b in r["baselines"].items():
        print(f"{name}: {b['params']['steps']} steps, val loss {b['final_val_loss']:.4g}, rollout MSE "
              f"{b['rollout_position_mse_m2']:.3g} m² (zero motion {b['rollout_zero_motion_mse_m2']:.3g}), "
              f"{b['s_per_step_median']:.3f} s/step")
    print(f"train_baselines: {r['wall_s']:.0f} s")


if __name__ == "__main__":
    run_cli(main, "train_baselines")
