"""The pipeline's headline figures, read from the stage reports: `reports/headline.json` (the one DVC metrics file, so
`dvc metrics show` is a table a person can read) and `reports/RESULTS.md` (the GPU runs' headline figures first, then
these figures, then every GPU report: `wc/results_page.py`). Written from the JSON, never by hand."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wc.atomic import write_atomic
from wc.paths import SUMMARY
from wc.reports import write_json_atomic
from wc.results_page import gpu_headlines, read_policy_report, results_markdown, run_folder_headlines
from wc.smoke import REPORT_KEY


@dataclass(frozen=True)
class Headline:
    """One figure: its key in headline.json, the report it comes from and the dotted path to it there. A wall-clock
    rate (`metric` false) differs on every machine, so it is shown in RESULTS.md but kept out of the DVC metrics
    file, where `dvc metrics diff` would report it changed between any two machines' runs."""

    key: str
    report: str
    path: str
    label: str
    metric: bool = True


HEADLINES = (
    Headline("simulate.accepted", "simulate.json", "accepted", "source episodes accepted"),
    Headline("simulate.episodes", "simulate.json", "episodes", "source episodes simulated"),
    Headline("simulate.episodes_per_min", "simulate.json", "episodes_per_min",
             "simulated episodes per minute (this machine)", metric=False),
    Headline("train.best_val_loss", "train.json", "best_val_loss", "WorldContact best validation loss"),
    Headline("train.constant_velocity_val_loss", "train.json", "constant_velocity_val_loss",
             "constant velocity, same validation windows"),
    Headline("train.rollout_position_mse_m2", "train.json", "rollout_position_mse_m2",
             "held-out rollout position MSE (m²), training's selection"),
    Headline("evaluate.worldcontact_position_mse_m2", "metrics.json", "methods.worldcontact.position_mse_m2",
             "WorldContact held-out position MSE (m²)"),
    Headline("evaluate.constant_velocity_position_mse_m2", "metrics.json",
             "methods.constant_velocity.position_mse_m2", "constant velocity held-out position MSE (m²)"),
    Headline("evaluate.worldcontact_penetration_rate_pct", "metrics.json",
             "methods.worldcontact.penetration_rate_pct", "WorldContact penetration rate (%)"),
    Headline("evaluate.whole_episode_mean_task_ratio", "metrics.json", "whole_episode.mean_task_ratio",
             "whole held-out episodes: best baseline's position MSE / WorldContact's, mean over tasks"),
    Headline("expand.generated", "expand.json", "generated", "generated episodes"),
    Headline("expand.accepted", "expand.json", "accepted", "generated episodes accepted"),
    Headline("expand.trajectories_per_min", "expand.json", "trajectories_per_min",
             "generated trajectories per minute (this machine)", metric=False),
    Headline("teacher_check.plans", "teacher_check.json", "plans", "teacher check: plans replayed in Newton"),
    Headline("teacher_check.agreement", "teacher_check.json", "agreement", "teacher check: verdicts agree"),
    Headline("teacher_check.precision", "teacher_check.json", "precision",
             "teacher check: WorldContact-accepted plans Newton accepts"),
    Headline("dataset.generated_episodes", "dataset.json", "generated_episodes", "generated episodes in the dataset"),
    Headline("policy.success_rate_source", "policy.json", "success_rate.source", "policy success, source data"),
    Headline("policy.success_rate_expanded", "policy.json", "success_rate.expanded", "policy success, expanded data"),
)


def _lookup(data: Any, path: str) -> Any:
    for part in path.split("."):
        if not isinstance(data, dict) or part not in data:
            return None
        data = data[part]
    return None if isinstance(data, (dict, list)) else data


def headline_reports(reports: Path) -> dict[str, Any]:
    """{report file: its JSON, None where missing} for every report HEADLINES reads. A report that exists but is
    not JSON raises ValueError naming it."""
    loaded: dict[str, Any] = {}
    for name in dict.fromkeys(h.report for h in HEADLINES):
        path = reports / name
        try:
            loaded[name] = json.loads(path.read_text()) if path.is_file() else None
        except json.JSONDecodeError as error:
            raise ValueError(f"{path} is not valid JSON ({error}): rerun its stage") from error
    return loaded


def headline_figures(reports: Path) -> dict[str, Any]:
    """{key: value} for every HEADLINES entry; None where its report or key is missing."""
    loaded = headline_reports(reports)
    return {h.key: _lookup(loaded[h.report], h.path) for h in HEADLINES}


def smoke_runs(reports: Path) -> dict[str, str]:
    """{report file: its smoke-run label} for the HEADLINES reports a smoke run wrote (wc.smoke)."""
    return {name: str(data[REPORT_KEY]) for name, data in headline_reports(reports).items()
            if isinstance(data, dict) and data.get(REPORT_KEY)}


def write_summary(reports: Path, headline: Path, results: Path) -> dict[str, Any]:
    """Write headline.json (the `metric` figures: DVC's metrics) and RESULTS.md (all of them), atomically; returns
    the figures. A GPU report of no declared kind, or without one of its kind's headline fields, is a HeadlineError (a
    ValueError) and nothing is written."""
    figures = headline_figures(reports)
    text = results_markdown(gpu_headlines(reports), figures, HEADLINES, read_policy_report(reports),
                            smoke_runs(reports), run_folder_headlines(reports.parent / "runs"))
    write_json_atomic(headline, {h.key: figures[h.key] for h in HEADLINES if h.metric})
    write_atomic(results, lambda p: p.write_text(text))
    return figures


def run(reports: str | Path = SUMMARY["reports"], headline: str | Path = SUMMARY["headline"],
        results: str | Path = SUMMARY["results"]) -> dict[str, Any]:
    """`write_summary` as the stage runs it; returns the figures and where they went."""
    return {"figures": write_summary(Path(reports), Path(headline), Path(results)), "headline": str(headline),
            "results": str(results)}


def summary_line(r: dict[str, Any]) -> str:
    """The line `python -m stages.summary` prints."""
    figures = r["figures"]
    missing = [k for k, v in figures.items() if v is None]
    return (f"summary: {len(figures) - len(missing)} of {len(figures)} headline figures"
            f"{' (missing: ' + ', '.join(missing) + ')' if missing else ''} -> {r['headline']}, {r['results']}")
