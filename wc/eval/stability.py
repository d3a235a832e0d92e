"""Long-rollout stability: per-step curves of position error, penetration and edge strain, and the step at
which a method first diverges (non-finite state, an edge strained beyond a bound, or too much penetration)."""

from __future__ import annotations

import csv
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wc.eval.metrics import finite_or_none

CSV_HEADER = ["method", "task", "episode", "start_frame", "step", "time_s", "position_mse_m2",
              "penetration_rate_pct", "max_edge_strain", "diverged"]


def max_edge_strain(x: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray) -> np.ndarray:
    """(T,) max over edges of |length / rest length − 1| for x (T, N, 3), edges (E, 2), rest_lengths (E,) m;
    NaN for frames with non-finite positions."""
    x = np.asarray(x, np.float64)
    edges = np.asarray(edges, np.int64)
    if len(edges) == 0:
        return np.zeros(len(x))
    with np.errstate(over="ignore", invalid="ignore"):
        length = np.linalg.norm(x[:, edges[:, 1]] - x[:, edges[:, 0]], axis=-1)
        strain = np.abs(length / np.maximum(np.asarray(rest_lengths, np.float64), 1e-12) - 1.0).max(axis=1)
    return np.where(np.isfinite(x).all(axis=(1, 2)), strain, np.nan)


def first_divergence(finite: np.ndarray, strain: np.ndarray, penetration_pct: np.ndarray, strain_bound: float,
                     penetration_bound_pct: float) -> int | None:
    """First step (1-based) whose state is non-finite, has an edge strain above strain_bound or more than
    penetration_bound_pct of cloth area penetrating; None if the rollout never diverges. Arrays (S,)."""
    bad = ~np.asarray(finite, bool)
    with np.errstate(invalid="ignore"):
        bad |= np.asarray(strain) > strain_bound
        bad |= np.asarray(penetration_pct) > penetration_bound_pct
    hits = np.flatnonzero(bad)
    return int(hits[0]) + 1 if len(hits) else None


@dataclass(frozen=True)
class StabilityCurve:
    """One long rollout of one method: per-step (S,) curves, steps 1..S, and its divergence step (1-based)."""

    method: str
    task: str
    episode: str
    start_frame: int
    position_mse_m2: np.ndarray
    penetration_rate_pct: np.ndarray
    max_edge_strain: np.ndarray
    divergence_step: int | None

    @property
    def steps(self) -> int:
        return len(self.position_mse_m2)


def csv_rows(curves: Iterable[StabilityCurve], dt: float) -> list[list[Any]]:
    """Rows of reports/stability.csv (CSV_HEADER): one per method, rollout and step; empty cells for NaN."""
    def cell(value: float) -> float | str:
        v = finite_or_none(float(value))
        return "" if v is None else v

    rows = []
    for c in curves:
        for k in range(c.steps):
            diverged = c.divergence_step is not None and k + 1 >= c.divergence_step
            rows.append([c.method, c.task, c.episode, c.start_frame, k + 1, round((k + 1) * dt, 6),
                         cell(c.position_mse_m2[k]), cell(c.penetration_rate_pct[k]), cell(c.max_edge_strain[k]),
                         int(diverged)])
    return rows


def read_csv_curves(path: str | Path) -> tuple[list[StabilityCurve], float]:
    """The curves of a stability CSV written from `csv_rows` (a run's reports/stability.csv, or one a GPU job sent
    back) and its frame dt, so its figure can be drawn again; ValueError naming the file when it is not one."""
    with Path(path).open(newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != CSV_HEADER:
            raise ValueError(f"{path}: not a stability CSV (columns {reader.fieldnames}, expected {CSV_HEADER})")
        rows = list(reader)
    if not rows:
        raise ValueError(f"{path}: a stability CSV without rows")
    by_rollout: dict[tuple[str, str, str, int], list[dict[str, str]]] = {}
    for row in rows:
        by_rollout.setdefault((row["method"], row["task"], row["episode"], int(row["start_frame"])), []).append(row)

    def column(rs: list[dict[str, str]], name: str) -> np.ndarray:
        return np.array([float(r[name]) if r[name] != "" else np.nan for r in rs])

    curves = []
    for (method, task, episode, start), rs in by_rollout.items():
        rs.sort(key=lambda r: int(r["step"]))
        diverged = [int(r["step"]) for r in rs if r["diverged"] == "1"]
        curves.append(StabilityCurve(method, task, episode, start, column(rs, "position_mse_m2"),
                                     column(rs, "penetration_rate_pct"), column(rs, "max_edge_strain"),
                                     diverged[0] if diverged else None))
    first = rows[0]
    return curves, float(first["time_s"]) / int(first["step"])


def divergence_summary(curves: Iterable[StabilityCurve]) -> dict[str, dict[str, Any]]:
    """Per method: rollouts, how many diverged, the first divergence step per task (None: never) and the
    rollouts' steps."""
    out: dict[str, dict[str, Any]] = {}
    for c in curves:
        m = out.setdefault(c.method, {"rollouts": 0, "diverged": 0, "first_divergence_step": {}, "steps": {}})
        m["rollouts"] += 1
        m["diverged"] += int(c.divergence_step is not None)
        key = c.task if c.task not in m["first_divergence_step"] else f"{c.task}/{c.episode}@{c.start_frame}"
        m["first_divergence_step"][key] = c.divergence_step
        m["steps"][key] = c.steps
    return out
