"""The train stage's work (`python -m stages.train`): WorldContact trained on the source trajectories (base stage,
then the stage with the topology projection in the loop: wc.train.loop) -> the model, the report and the loss
curves. A run cut by `train.max_minutes` (or `stop_at_step`) leaves a resumable checkpoint and reports
"complete": False.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from wc.config import load_section, params_hash
from wc.model.config import ModelConfig
from wc.paths import TRAIN
from wc.reports import environment_info, write_json_atomic
from wc.train.config import TrainConfig
from wc.train.loop import train
from wc.train.plots import write_loss_curves

SECTIONS = ["model", "train"]
EXIT_RESUMABLE = 75  # EX_TEMPFAIL: stopped early with a complete checkpoint


def run(params: dict[str, Any], store: str | Path = TRAIN["store"], out: str | Path = TRAIN["out"],
        report: str | Path = TRAIN["report"], curves: str | Path = TRAIN["curves"], resume: bool = False,
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


def train_summary(r: dict[str, Any]) -> str:
    """The line `python -m stages.train` prints (none on ranks > 0)."""
    if r.get("complete") is False:
        return (f"train: stopped at step {r['step']} of {r['total_steps']} ({r['s_per_step_median']:.3f} s/step); "
                f"checkpoint in {r['partial']}: run again with --resume to go on")
    if not r:
        return ""
    return (f"train: {r['steps']['base']} + {r['steps']['projection']} steps, best val loss {r['best_val_loss']:.4g} "
            f"(zero motion {r['zero_motion_val_loss']:.4g}), rollout MSE {r['rollout_position_mse_m2']:.3g} m² "
            f"(zero motion {r['rollout_zero_motion_mse_m2']:.3g}), {r['s_per_step_median']:.3f} s/step, "
            f"{r['wall_s']:.0f} s")


def train_exit_status(r: dict[str, Any]) -> int:
    """EXIT_RESUMABLE when the run stopped early with its checkpoint, else 0."""
    return EXIT_RESUMABLE if r.get("complete") is False else 0
