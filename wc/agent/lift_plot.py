"""Per-episode lift curves (height of the objects' lowest vertex above the table) as CSV + PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wc.reports import pyplot, save_figure_atomic, write_csv_atomic


def write_lift_curves(curves: dict[str, tuple[np.ndarray, str]], dt: float, csv_path: str | Path,
                      png_path: str | Path) -> None:
    """curves: episode id -> (lowest vertex height above the table per frame [m], label)."""
    write_csv_atomic(csv_path, ["episode", "time_s", "lowest_vertex_m"],
                     ((eid, round(k * dt, 4), round(float(h), 5))
                      for eid, (heights, _) in curves.items() for k, h in enumerate(heights)))
    fig, ax = pyplot().subplots(figsize=(6, 3.5), dpi=120)
    for eid, (heights, label) in curves.items():
        ax.plot(np.arange(len(heights)) * dt, heights * 100, label=f"{eid} {label}")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("lowest vertex above table [cm]")
    ax.set_title("simulate: object lift per episode")
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure_atomic(fig, png_path)
