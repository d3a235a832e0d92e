"""Evaluation figures: long-rollout stability (per-step median and interquartile band, one line per method) and
speed against accuracy (one point per method)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from wc.eval.stability import StabilityCurve
from wc.reports import pyplot, save_figure_atomic

PANELS = (("position_mse_m2", "position MSE [m²]", True),
          ("penetration_rate_pct", "penetrating cloth area [%]", False),
          ("max_edge_strain", "max edge strain |l/l₀ − 1|", True))


def _stack(curves: Sequence[StabilityCurve], field: str) -> np.ndarray:
    """(rollouts, max steps) with NaN padding past each rollout's end."""
    out = np.full((len(curves), max(c.steps for c in curves)), np.nan)
    for i, c in enumerate(curves):
        out[i, : c.steps] = getattr(c, field)
    return out


def plot_stability(curves: Sequence[StabilityCurve], path: str | Path, dt: float,
                   strain_bound: float | None = None, penetration_bound_pct: float | None = None) -> Path:
    """Write the three-panel figure (error, penetration, strain against rollout time) to `path` (PNG)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    methods = list(dict.fromkeys(c.method for c in curves))
    for i, method in enumerate(methods):
        mine = [c for c in curves if c.method == method]
        for ax, (field, label, log) in zip(axes, PANELS):
            values = _stack(mine, field)
            if log:
                values = np.where(values > 0, values, np.nan)
            if np.isnan(values).all():
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN steps after every rollout diverged
                lo, mid, hi = np.nanpercentile(values, [25, 50, 75], axis=0)
            t = np.arange(1, values.shape[1] + 1) * dt
            ax.plot(t, mid, color=f"C{i}", label=method)  # one colour per method in every panel
            ax.fill_between(t, lo, hi, color=f"C{i}", alpha=0.15, linewidth=0)
    for ax, (field, label, log) in zip(axes, PANELS):
        ax.set_xlabel("rollout time [s]")
        ax.set_ylabel(label)
        if log:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    if strain_bound is not None:
        axes[2].axhline(strain_bound, color="k", linestyle="--", linewidth=0.8)
        axes[2].set_title(f"divergence above {strain_bound:g} (dashed)", fontsize=9)
    if penetration_bound_pct is not None:  # usually far above the curves: named, not drawn
        axes[1].set_title(f"divergence above {penetration_bound_pct:g} %", fontsize=9)
    handles = [plt.Line2D([], [], color=f"C{i}", label=m) for i, m in enumerate(methods)]
    axes[1].legend(handles=handles, fontsize=8)
    fig.suptitle(f"Long rollouts: per-step median over the {len(curves) // max(1, len(methods))} rollouts per "
                 "method that reach the step (band: 25-75 %)")
    return save_figure_atomic(fig, path)


SPEED_ACCURACY_HEADER = ["method", "kind", "simulated_s_per_wall_s", "position_mse_m2", "penetration_rate_pct"]
MARKERS = {"worldcontact": "o", "baseline": "^", "newton": "s", "zero_motion": "x", "constant_velocity": "+"}


def speed_accuracy_rows(methods: dict[str, dict[str, Any]], dt: float,
                        kinds: dict[str, str] | None = None) -> list[list[object]]:
    """One row per method: its kind, speed (simulated seconds per wall second, dt / s_per_step; inf for a method
    timed at zero) and its held-out position MSE and penetration rate (None where undefined)."""
    rows = []
    for name, m in methods.items():
        per_step = m["s_per_step"]
        speed = None if per_step is None else dt / per_step if per_step > 0 else float("inf")
        rows.append([name, (kinds or {}).get(name, ""), speed, m["position_mse_m2"], m["penetration_rate_pct"]])
    return rows


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the (speed, error) points no other point beats on both, fastest first."""
    order = sorted(range(len(points)), key=lambda i: (-points[i][0], points[i][1]))
    front, best = [], float("inf")
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def _finite(value: object) -> bool:
    return value is not None and bool(np.isfinite(float(value)))


def _speed_panel(ax: Any, rows: list[list[object]], column: int, label: str, log_y: bool) -> None:
    """One marker per row (kind -> shape, row -> colour; named in the legend, the Pareto front's also beside the
    marker) at (speed, rows[column]) and the Pareto front."""
    colours = {str(r[0]): f"C{i % 10}" for i, r in enumerate(rows)}  # the same colour in both panels
    shown = [(str(r[0]), str(r[1]), float(r[2]), float(r[column])) for r in rows
             if _finite(r[2]) and _finite(r[column]) and (float(r[column]) > 0 or not log_y)]
    for name, kind, speed, value in shown:
        ax.scatter(speed, value, color=colours[name], marker=MARKERS.get(kind, "o"), s=40, label=name)
    front = [shown[i] for i in pareto_front([(s, v) for _, _, s, v in shown])]
    if len(front) > 1:
        ax.step([s for _, _, s, _ in front], [v for _, _, _, v in front], where="post", color="k", linestyle="--",
                linewidth=0.8, label="Pareto front")
    for name, _, speed, value in front:
        ax.annotate(name, (speed, value), textcoords="offset points", xytext=(5, 4), fontsize=7)
    ax.set_xscale("log")
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel("speed [simulated s per wall s] (higher is faster)")
    ax.set_ylabel(label)
    ax.grid(alpha=0.3, which="both")


def plot_speed_accuracy(rows: list[list[object]], path: str | Path, rollouts: int | None = None) -> Path:
    """Speed against held-out position MSE (log-log) and against penetration, one labelled marker per method and
    setting (squares: Newton settings), Pareto fronts drawn; to `path` (PNG)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(15.0, 5.0), constrained_layout=True)
    _speed_panel(axes[0], rows, 3, "held-out position MSE [m²] (lower is better)", log_y=True)
    _speed_panel(axes[1], rows, 4, "penetrating cloth area [%] (lower is better)", log_y=False)
    axes[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)  # one key for both
    on = f" ({rollouts} held-out rollouts, the same for every method)" if rollouts else ""
    fig.suptitle(f"Speed against accuracy{on}; rollout only", fontsize=10)
    return save_figure_atomic(fig, path)
