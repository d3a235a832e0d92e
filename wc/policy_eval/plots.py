"""The success rates side by side: a CSV for DVC's plot and a bar chart PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wc.policy.comparison import flagged_title
from wc.reports import pyplot, save_figure_atomic, write_csv_atomic

CSV_HEADER = ["policy", "successes", "trials", "success_rate"]


def write_success_table(path: str | Path, policies: dict[str, dict[str, Any]]) -> Path:
    """One row per policy: successes, trials, success rate."""
    return write_csv_atomic(path, CSV_HEADER, [[name, p["successes"], p["trials"], p["success_rate"]]
                                               for name, p in policies.items()])


def plot_success_rates(path: str | Path, policies: dict[str, dict[str, Any]], task: str,
                       expanded_equals_source: bool | None = None) -> Path:
    """Bar chart of the success rate per policy, each bar labelled successes / trials; the title says when the
    source and expanded policies trained on the same episodes."""
    plt = pyplot()
    names = list(policies)
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(names), 3.2))
    bars = ax.bar(names, [policies[n]["success_rate"] for n in names], color="#4878a8")
    for bar, name in zip(bars, names):
        ax.annotate(f"{policies[name]['successes']}/{policies[name]['trials']}",
                    (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom")
    ax.set_ylim(0, 1.1)
    ax.set_ylabel("success rate")
    ax.set_title(flagged_title(f"closed-loop {task}: policy per training dataset", expanded_equals_source))
    fig.tight_layout()
    return save_figure_atomic(fig, path)
