"""Which stages' figures are smoke runs at the params in use (params section `smoke_run`).

A smoke run exercises a stage end to end at a size too small for its figures to mean anything (one closed-loop
trial per policy, a few training steps). Each listed stage writes `smoke_run: <label>` into its report, and
`reports/RESULTS.md` (wc.summary) shows the label beside every figure read from such a report.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from wc.config import ParamsError, load_section
from wc.paths import STAGES

REPORT_KEY = "smoke_run"


@dataclass(frozen=True)
class SmokeRunConfig:
    label: str  # what the reports and RESULTS.md say, e.g. "smoke run (CPU default): not a result"
    stages: list[str]  # stages (names as in wc.paths.STAGES) whose figures are smoke runs at these params

    def validate(self) -> None:
        unknown = [s for s in self.stages if s not in STAGES]
        if unknown:
            raise ValueError(f"stages: unknown stage {unknown[0]!r} (stages: {sorted(STAGES)})")
        if self.stages and not self.label.strip():
            raise ValueError("label must say what the listed stages' figures are")


def smoke_label(params: dict[str, Any], stage: str) -> dict[str, str]:
    """`{"smoke_run": label}` to merge into `stage`'s report when params `smoke_run.stages` lists it, else {}."""
    if stage not in STAGES:
        raise ParamsError(f"smoke_label: unknown stage {stage!r}")
    if "smoke_run" not in params:
        return {}
    cfg = load_section(params, "smoke_run", SmokeRunConfig)
    return {REPORT_KEY: cfg.label} if stage in cfg.stages else {}
