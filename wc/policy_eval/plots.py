"""The success rates side by side: a CSV for DVC's plot, a JSON for DVC's metrics and a bar chart PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wc.policy.comparison import flagged_title
from wc.reports import pyplot, save_figure_atomic, write_csv_atomic, write_json_atomic

CSV_HEADER = ["policy", "successes", "trials", "success_rate", "ci95_low", "ci95_high"]


def _figures(p: dict[str, Any]) -> list[Any]:
    """A policy's CSV_HEADER[1:] values: successes, trials, success rate, its 95 % Wilson interval."""
    return [p["successes"], p["trials"], p["success_rate"], *p["ci95"]]


def write_success_table(path: str | Path, policies: dict[str, dict[str, Any]]) -> Path:
    """One row per policy: successes, trials, success rate and its 95 % Wilson interval."""
    return write_csv_atomic(path, CSV_HEADER, [[name, *_figures(p)] for name, p in policies.items()])


def write_success_metrics(path: str | Path, policies: dict[str, dict[str, Any]]) -> None:
    """{policy: {successes, trials, success_rate, ci95_low, ci95_high}}: the per-arm figures `dvc metrics show` and
    `dvc metrics diff` compare (no timings: two machines' runs of the same params do not differ)."""
    write_json_atomic(path, {name: dict(zip(CSV_HEADER[1:], _figures(p))) for name, p in policies.items()})


def plot_success_rates(path: str | Path, policies: dict[str, dict[str, Any]], task: str,
                       expanded_equals_source: bool | None = None) -> Path:
    """Bar chart of the success rate per policy with its 95 % Wilson interval, each bar labelled successes / trials
    (and the training episodes where known); the title says when the source and expanded policies trained on the
    same episodes."""
    plt = pyplot()
    names = list(policies)
    rates = [policies[n]["success_rate"] for n in names]
    errors = [[r - policies[n]["ci95"][0] for n, r in zip(names, rates)],
              [policies[n]["ci95"][1] - r for n, r in zip(names, rates)]]
    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(names), 3.2))
    bars = ax.bar(names, rates, yerr=errors, capsize=4, color="#4878a8")
    for bar, name in zip(bars, names):
        episodes = policies[name].get("episodes")
        label = f"{policies[name]['successes']}/{policies[name]['trials']}" + (f"\n{episodes} ep." if episodes else "")
        ax.annotate(label, (bar.get_x() + bar.get_width() / 2, policies[name]["ci95"][1] + 0.02), ha="center",
                    va="bottom", fontsize=8)
    ax.set_ylim(0, 1.3)
    ax.set_ylabel("success rate")
    ax.set_title(flagged_title(f"closed-loop {task}: policy per training dataset", expanded_equals_source))
    fig.tight_layout()
    return save_figure_atomic(fig, path)
