"""Training curves: train / validation / zero-motion loss per evaluation, as CSV + PNG (a DVC plot)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wc.reports import pyplot, save_figure_atomic, write_csv_atomic

COLUMNS = ["step", "stage", "train_loss", "val_loss", "zero_motion_loss", "constant_velocity_loss",
           "rollout_position_mse_m2"]


def write_loss_curves(history: list[dict[str, Any]], csv_path: Path) -> None:
    """`csv_path` and its .png sibling from the per-evaluation history of wc.train.loop."""
    write_csv_atomic(csv_path, COLUMNS, ([h.get(c, float("nan")) for c in COLUMNS] for h in history))
    fig, ax = pyplot().subplots(figsize=(6, 3.5), dpi=120)
    steps = [h["step"] for h in history]
    for key, style in (("train_loss", "-"), ("val_loss", "-"), ("zero_motion_loss", "--"), ("constant_velocity_loss", ":")):
        ax.plot(steps, [h.get(key, float("nan")) for h in history], style, label=key.replace("_", " "))
    switch = next((h["step"] for h in history if h["stage"] == "projection"), None)
    if switch is not None:
        ax.axvline(switch, color="grey", lw=0.8, label="projection stage")
    ax.set_yscale("log")
    ax.set_xlabel("optimisation step")
    ax.set_ylabel("loss (λ = 1e4, m² and (m/s)²)")
    ax.set_title("train: WorldContact segment loss")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure_atomic(fig, csv_path.with_suffix(".png"))
