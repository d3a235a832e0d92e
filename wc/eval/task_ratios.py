"""How far one method (the subject, WorldContact) is below the best baseline, task by task.

Per task, ratio = the best baseline's position MSE / the subject's (> 1: the subject is better). The summary figure is
the mean of the per-task ratios, so that one task whose errors dwarf the others cannot carry it (as a ratio of MSEs
pooled over tasks lets it); the worst task's ratio and the pooled ratio are reported beside it. A diverged rollout
(MSE None) counts as infinitely wrong: a diverged baseline is never the best, a diverged subject has ratio 0; a task
where both diverged has no ratio and is left out of the mean and the worst.
"""

from __future__ import annotations

import math
from typing import Any

from wc.eval.metrics import finite_or_none


def error_ratio(baseline: float | None, subject: float | None) -> float:
    """best baseline MSE / subject MSE (m² / m²), None meaning diverged (infinite)."""
    b = math.inf if baseline is None else baseline
    s = math.inf if subject is None else subject
    if math.isinf(s):
        return 0.0 if not math.isinf(b) else math.nan
    return b / s if s > 0 else (math.inf if b > 0 else math.nan)


def best_baseline(mse: dict[str, float | None]) -> tuple[str | None, float | None]:
    """(name, MSE) of the lowest finite MSE among `mse` (method -> MSE or None); (None, None) if all diverged."""
    finite = {name: value for name, value in mse.items() if value is not None}
    if not finite:
        return None, None
    name = min(finite, key=lambda n: (finite[n], n))
    return name, finite[name]


def task_ratios(per_task: dict[str, dict[str, float | None]], pooled: dict[str, float | None], subject: str,
                baselines: list[str]) -> dict[str, Any]:
    """Per-task and summary ratios of `subject` against `baselines`.

    per_task: method -> task -> position MSE (m², None = diverged), over the same rollouts for every method;
    pooled: method -> position MSE over all of them. Returns {mean_task_ratio, worst_task_ratio, pooled_ratio,
    per_task: {task: {ratio, best_baseline, best_baseline_mse_m2, subject_mse_m2}}} (ratios None where undefined).
    """
    missing = [m for m in [subject, *baselines] if m not in per_task or m not in pooled]
    if missing or not baselines:
        raise ValueError(f"task ratios need the subject and at least one baseline; missing {missing or 'baselines'}")
    tasks = sorted(per_task[subject])
    rows, ratios = {}, []
    for task in tasks:
        name, best = best_baseline({b: per_task[b].get(task) for b in baselines})
        subject_mse = per_task[subject][task]
        ratio = error_ratio(best, subject_mse)
        ratios.append(ratio)
        rows[task] = {"ratio": finite_or_none(ratio), "best_baseline": name, "best_baseline_mse_m2": best,
                      "subject_mse_m2": subject_mse}
    _, pooled_best = best_baseline({b: pooled[b] for b in baselines})
    defined = [r for r in ratios if not math.isnan(r)]  # a task where the subject and every baseline diverged: none
    return {"mean_task_ratio": finite_or_none(sum(defined) / len(defined)) if defined else None,
            "worst_task_ratio": finite_or_none(min(defined)) if defined else None,
            "pooled_ratio": finite_or_none(error_ratio(pooled_best, pooled[subject])),
            "per_task": rows}
