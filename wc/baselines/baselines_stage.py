"""The train_baselines stage's work (`python -m stages.train_baselines`): every baseline named in params
`baselines` trained on the source trajectories (wc.baselines.train) -> models/baselines/<name>/ and the report.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from wc.baselines import BASELINES
from wc.baselines.config import BaselinesConfig
from wc.baselines.train import train_baseline
from wc.config import ParamsError, load_section, params_hash
from wc.paths import TRAIN_BASELINES
from wc.reports import environment_info, write_json_atomic
from wc.smoke import smoke_label
from wc.train.config import TrainConfig

SECTIONS = ["baselines", "train"]


def run(params: dict[str, Any], store: str | Path = TRAIN_BASELINES["store"], out: str | Path = TRAIN_BASELINES["out"],
        report: str | Path = TRAIN_BASELINES["report"]) -> dict[str, Any]:
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
              "environment": environment_info(cfg.device), "models": str(out), **smoke_label(params, "train_baselines")}
    write_json_atomic(report, result)
    return result


def train_baselines_summary(r: dict[str, Any]) -> str:
    """The lines `python -m stages.train_baselines` prints: one per baseline, then the wall time."""
    lines = [f"{name}: {b['steps_done']} steps ({b['stopped_by']}), best val loss {b['best_val_loss']:.4g} (zero "
             f"motion {b['val_loss_zero_motion']:.4g}, constant velocity {b['val_loss_constant_velocity']:.4g}), "
             f"kept step {b['best_step']} (by {b['recipe']['select_by']}), rollout MSE "
             f"{b['rollout_position_mse_m2']:.3g} m² (zero motion {b['rollout_zero_motion_mse_m2']:.3g}), "
             f"{b['s_per_step_median']:.3f} s/step" for name, b in r["baselines"].items()]
    return "\n".join([*lines, f"train_baselines: {r['wall_s']:.0f} s"])
