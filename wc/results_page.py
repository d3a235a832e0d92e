"""`reports/RESULTS.md`: the headline figures of the GPU runs first (what beat what, by how much, with intervals and
the protocol, each linking its write-up), then the last `dvc repro`'s figures (labelled a smoke run when its policy
evaluation ran too few trials to measure a success rate), then every GPU report with its kind's headline
(`wc/report_kinds.py`). Written from the JSON by the summary stage, never by hand."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wc.report_kinds import kind_named, report_headline

SMOKE_TRIALS = 20  # fewer closed-loop trials per policy than this: a smoke run (a 95 % interval wider than ~0.4)


@dataclass(frozen=True)
class Featured:
    """A GPU report whose headline leads the page: its title, file in reports/gpu/ and write-up (relative to
    reports/)."""

    title: str
    report: str
    write_up: str


FEATURED = (
    Featured("Policy trained on source, expanded and Newton-150 data", "policy_h100_three_arms.json",
             "gpu/policy_h100_three_arms.md"),
    Featured("Table 1: held-out rollouts of six contact tasks, against the baselines", "metrics_h100_table1_solo.json",
             "gpu/table1_h100.md"),
    Featured("Expansion 25 -> 150 lift_handle episodes (Newton at 20 VBD iterations)",
             "expand_h100_lift_handle_25to150.json", "gpu/lift_expansion.md"),
    Featured("Teacher check of those 125 generated plans", "teacher_check_h100_lift_handle_25to150.json",
             "gpu/lift_expansion.md"),
    Featured("Training speed, static-shape path against the reference path", "train_speed_h100.json",
             "gpu/train_speed_h100.md"),
    Featured("Simulate on the Ray executor, workers sharing one GPU", "simulate_ray_h100.json",
             "gpu/simulate_ray_scaling.md"),
)


def gpu_headlines(reports: Path) -> list[tuple[str, str, str]]:
    """(file name, kind, headline) for every JSON report in reports/gpu/; HeadlineError for one of no declared
    kind or without a declared field."""
    return [(path.name, *report_headline(path)) for path in sorted((reports / "gpu").glob("*.json"))]


def smoke_label(policy: dict[str, Any] | None) -> str:
    """The paragraph that says what the last `dvc repro`'s figures can show."""
    trials = policy.get("trials") if policy else None
    if trials is None:
        return "The figures of the last `dvc repro` (no policy evaluation report)."
    if trials < SMOKE_TRIALS:
        return (f"**A smoke run**: the last `dvc repro` (the small CPU default unless params say otherwise) ran "
                f"{trials} closed-loop trial(s) per policy. Its figures show that every stage runs end to end; they "
                "do not measure what the method achieves (the GPU runs above do).")
    return f"The figures of the last `dvc repro`, {trials} closed-loop trials per policy."


def _fmt(value: Any) -> str:
    if value is None:
        return "–"
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def results_markdown(rows: Sequence[tuple[str, str, str]], figures: dict[str, Any], labels: Sequence[Any],
                     policy: dict[str, Any] | None, smoke: dict[str, str] | None = None,
                     runs: Sequence[tuple[str, str]] = ()) -> str:
    """The page: featured GPU headlines, the run folders' policy results (`runs` from `run_folder_headlines`), the
    last repro's `figures` (one row per `labels` entry: a Headline with
    key, label, report, path) under its smoke label, each marked with its report's smoke-run label (`smoke`:
    {report file: label}, params `smoke_run`) or `measured`, then every GPU report (`rows` from `gpu_headlines`)."""
    smoke = smoke or {}
    by_name = {name: (kind, line) for name, kind, line in rows}
    lines = ["# Results", "", "Written by `python -m stages.summary` from the reports' JSON; do not edit by hand.", "",
             "## Headline figures (GPU runs, `reports/gpu/`)", ""]
    for f in FEATURED:
        if f.report in by_name:
            lines.append(f"- **{f.title}**: {by_name[f.report][1]}. [Write-up]({f.write_up}), `gpu/{f.report}`.")
    if runs:
        lines += ["", "## GPU runs through DVC (`runs/`: each one's `dvc.lock` records its params, code and outputs)", ""]
        lines += [f"- **`{name}`** ([config](../{name}/config.yaml)): {line}." for name, line in runs]
    lines += ["", "## The last `dvc repro`", "", smoke_label(policy)]
    if smoke:
        lines += ["", "Smoke runs (params `smoke_run`: too few trials, plans or steps for their figures to mean "
                      f"anything): {', '.join(f'`{name}`' for name in smoke)}."]
    lines += ["", "| figure | value | what it is | report |", "|---|---|---|---|"]
    lines += [f"| {h.label} | {_fmt(figures.get(h.key))} | {smoke.get(h.report, 'measured')} | `{h.report}` "
              f"`{h.path}` |" for h in labels]
    lines += ["", "## Every GPU report (`reports/gpu/`)", "",
              "Each JSON report holds its command or params, device and versions; its kind declares the fields of "
              "its headline (`wc/report_kinds.py`).", "", "| report | kind | headline |", "|---|---|---|"]
    lines += [f"| `{name}` | {kind} | {line} |" for name, kind, line in rows]
    return "\n".join(lines) + "\n"


def run_folder_headlines(runs: Path) -> list[tuple[str, str]]:
    """(run folder, headline) for every run folder's policy evaluation (`runs/<name>/reports/policy.json`: a GPU
    configuration run through DVC, its record `runs/<name>/dvc.lock`), read as a "policy evaluation" report."""
    kind = kind_named("policy evaluation")
    return [(f"runs/{path.parent.parent.name}", kind.headline(json.loads(path.read_text()), str(path)))
            for path in sorted(runs.glob("*/reports/policy.json"))]


def read_policy_report(reports: Path) -> dict[str, Any] | None:
    """reports/policy.json, or None when the policy_eval stage has not run."""
    path = reports / "policy.json"
    return json.loads(path.read_text()) if path.is_file() else None
