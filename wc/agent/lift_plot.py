"""Per-episode lift curves (height of the objects' lowest vertex above the table) as CSV + PNG."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np


def write_lift_curves(curves: dict[str, tuple[np.ndarray, str]], dt: float, csv_path: str | Path,
                      png_path: str | Path) -> None:
    """curves: episode id -> (lowest vertex height above the table per frame [m], label)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    csv_path, png_path = Path(csv_path), Path(png_path)
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = csv_path.with_name(f".{csv_path.name}.tmp-{os.getpid()}")
    with tmp.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["episode", "time_s", "lowest_vertex_m"])
        for eid, (heights, _) in curves.items():
            writer.writerows((eid, round(k * dt, 4), round(float(h), 5)) for k, h in enumerate(heights))
    os.replace(tmp, csv_path)
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    for eid, (heights, label) in curves.items():
        ax.plot(np.arange(len(heights)) * dt, heights * 100, label=f"{eid} {label}")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("lowest vertex above table [cm]")
    ax.set_title("simulate: object lift per episode")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp_png = png_path.with_name(f".{png_path.name}.tmp-{os.getpid()}.png")
    fig.savefig(tmp_png)
    plt.close(fig)
    os.replace(tmp_png, png_path)
