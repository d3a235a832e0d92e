"""Stage `train`: WorldContact on data/source/trajectories.zarr -> models/worldcontact/ and reports/train.json.

    python -m stages.train [--params params.yaml] [--set train.base.steps=100 ...] [--resume]
    torchrun --nproc-per-node 8 -m stages.train --params params/gpu.yaml     # DistributedDataParallel
    python -m stages.train --set train.max_minutes=8 [--resume]              # a chunk of a long run: exit 75 = go on

A run cut by `train.max_minutes` (or `--stop-at-step`) leaves a complete checkpoint in `<out>.partial/` and exits
with status 75 (EX_TEMPFAIL); `--resume` continues it to the same result as one uninterrupted run.

Base stage, then the stage with the topology projection in the loop (wc.train.loop); the loss
curves go to reports/train_loss.{csv,png} (a DVC plot).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from wc.cli import run_cli
from wc.config import add_params_arguments, load_section, params_hash, read_params
from wc.model.config import ModelConfig
from wc.reports import environment_info, write_json_atomic
from wc.train.config import TrainConfig
from wc.train.loop import train
from wc.train.plots import write_loss_curves

SECTIONS = ["model", "train"]
EXIT_RESUMABLE = 75  # EX_TEMPFAIL: stopped early with a complete checkpoint


def run(params: dict[str, Any], store: str | Path = "data/source/trajectories.zarr",
        out: str | Path = "models/worldcontact", report: str | Path = "reports/train.json",
        curves: str | Path = "reports/train_loss.csv", resume: bool = False,
        stop_at_step: int | None = None) -> dict[str, Any]:
    """Train and write the model, the report and the loss curves; returns the report (empty on ranks > 0; with
    "complete": False when the run stopped early, leaving its checkpoint for --resume)."""
    model_cfg = load_section(params, "model", ModelConfig)
    cfg = load_section(params, "train", TrainConfig)
    if not Path(store).exists():
        raise FileNotFoundError(f"train: trajectory store not found: {store} (run the validate stage first)")
    start = time.perf_counter()
    digest = params_hash(params, SECTIONS)
    result = train(store, out, model_cfg, cfg, resume=resume, meta={"params_hash": digest}, stop_at_step=stop_at_step)
    if not result or result.get("complete") is False:
        return result
    result.update(wall_s=time.perf_counter() - start, params_hash=digest, environment=environment_info(cfg.device),
                  model=str(out))
    write_loss_curves(result["history"], Path(curves))
    write_json_atomic(report, result)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--out", default="models/worldcontact")
    parser.add_argument("--report", default="reports/train.json")
    parser.add_argument("--curves", default="reports/train_loss.csv")
    parser.add_argument("--resume", action="store_true", help="continue from <out>.partial/last_state.pt")
    parser.add_argument("--stop-at-step", type=int, default=None, help="stop cleanly after this step (resumable)")
    args = parser.parse_args(argv)
    r = run(read_params(args.params, args.overrides), args.store, args.out, args.report, args.curves, args.resume,
            args.stop_at_step)
    if r.get("complete") is False:
        print(f"train: stopped at step {r['step']} of {r['total_steps']} ({r['s_per_step_median']:.3f} s/step); "
              f"checkpoint in {r['partial']}: run again with --resume to go on")
        sys.exit(EXIT_RESUMABLE)
    if r:
        print(f"train: {r['steps']['base']} + {r['steps']['projection']} steps, best val loss {r['best_val_loss']:.4g} "
              f"(zero motion {r['zero_motion_val_loss']:.4g}), rollout MSE {r['rollout_position_mse_m2']:.3g} m² "
              f"(zero motion {r['rollout_zero_motion_mse_m2']:.3g}), {r['s_per_step_median']:.3f} s/step, "
              f"{r['wall_s']:.0f} s")


if __name__ == "__main__":
    run_cli(main, "train")
