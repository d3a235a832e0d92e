"""The headline figures (wc/summary.py): read from the stage reports, missing ones named, the one DVC metrics file."""

from __future__ import annotations

import json

import pytest
import yaml

from stages.summary import main
from tests.conftest import ROOT, load_params
from wc.config import ParamsError
from wc.smoke import smoke_label
from wc.summary import HEADLINES, headline_figures, write_summary


def _reports(tmp_path):
    reports = tmp_path / "reports"
    (reports / "gpu").mkdir(parents=True)
    (reports / "expand.json").write_text(json.dumps({"generated": 40, "accepted": 31, "trajectories_per_min": 12.5}))
    (reports / "metrics.json").write_text(json.dumps({"methods": {"worldcontact": {"position_mse_m2": 2e-4},
                                                                  "constant_velocity": {"position_mse_m2": 6e-4}}}))
    (reports / "gpu" / "validate_h100_run.json").write_text(json.dumps({"episodes": 9, "accepted": 7, "wall_s": 3.0}))
    (reports / "policy.json").write_text(json.dumps({"trials": 1, "success_rate": {"source": 0.0, "expanded": 1.0}}))
    return reports


def test_figures_come_from_the_reports_and_missing_ones_are_none(tmp_path):
    figures = headline_figures(_reports(tmp_path))
    assert set(figures) == {h.key for h in HEADLINES}
    assert figures["expand.accepted"] == 31 and figures["expand.generated"] == 40
    assert figures["evaluate.worldcontact_position_mse_m2"] == 2e-4
    assert figures["train.best_val_loss"] is None and figures["teacher_check.precision"] is None


def test_summary_writes_the_metric_and_the_results_page(tmp_path, capsys):
    reports = _reports(tmp_path)
    main(["--reports", str(reports), "--headline", str(reports / "headline.json"),
          "--results", str(reports / "RESULTS.md")])
    headline = json.loads((reports / "headline.json").read_text())
    assert headline["expand.accepted"] == 31 and "expand.trajectories_per_min" not in headline  # a wall-clock rate
    page = (reports / "RESULTS.md").read_text()
    assert "| generated episodes accepted | 31 |" in page and "| policy success, expanded data | 1 |" in page
    assert "| generated trajectories per minute (this machine) | 12.5 |" in page  # shown, not a DVC metric
    assert "| `validate_h100_run.json` | validate | 7 of 9 episodes accepted |" in page
    assert "**A smoke run**" in page and "ran 1 closed-loop trial(s) per policy" in page
    assert "missing: " in capsys.readouterr().out


def test_the_run_folders_policy_results_are_on_the_page(tmp_path):
    """runs/<name>/reports/policy.json (a GPU run through DVC) is read as a policy evaluation: per arm with its
    interval, under the run's name, above the last repro's figures; one lacking a declared field is named."""
    reports = _reports(tmp_path)
    run = tmp_path / "runs" / "gpu_x" / "reports"
    run.mkdir(parents=True)
    arm = {"successes": 45, "trials": 50}
    policy = {"policies": {"source": arm, "expanded": {**arm, "successes": 48}}, "policy_type": "act",
              "task": "lift_handle", "lift_height_m": 0.05, "hold_s": 2.0}
    (run / "policy.json").write_text(json.dumps(policy))
    write_summary(reports, reports / "h.json", reports / "R.md")
    page = (reports / "R.md").read_text()
    line = next(x for x in page.splitlines() if x.startswith("- **`runs/gpu_x`**"))
    assert "source 45/50 (0.79-0.96)" in line and "expanded 48/50 (0.87-0.99)" in line
    assert page.index("runs/gpu_x") < page.index("## The last `dvc repro`")
    del policy["task"]
    (run / "policy.json").write_text(json.dumps(policy))
    with pytest.raises(ValueError, match="task"):
        write_summary(reports, reports / "h.json", reports / "R.md")


def test_a_corrupt_report_is_named(tmp_path):
    reports = _reports(tmp_path)
    (reports / "train.json").write_text("{not json")
    with pytest.raises(ValueError, match="train.json is not valid JSON"):
        write_summary(reports, reports / "h.json", reports / "R.md")
    assert not (reports / "h.json").exists()


def test_the_metrics_files_hold_no_wall_clock_rate_and_the_summary_reads_every_report():
    """DVC's metrics are the headline figures and the per-arm policy success; no timing, so `dvc metrics diff` between
    two machines' runs of the same params shows nothing."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    with_metrics = {name: [next(iter(m)) for m in s.get("do", s)["metrics"]] for name, s in stages.items()
                    if "metrics" in s.get("do", s)}
    assert with_metrics == {"summary": ["reports/headline.json"], "policy_eval": ["reports/policy_success.json"]}
    timed = [h.key for h in HEADLINES if h.metric and any(w in h.path for w in ("per_min", "wall", "_s_per", "seconds"))]
    assert timed == [] and {h.key for h in HEADLINES if not h.metric} == {"simulate.episodes_per_min",
                                                                            "expand.trajectories_per_min"}
    deps = set(stages["summary"]["deps"])
    assert {f"reports/{h.report}" for h in HEADLINES} <= deps
    outs = {next(iter(o)) if isinstance(o, dict) else o for s in stages.values() for o in s.get("do", s).get("outs", [])}
    assert {f"reports/{h.report}" for h in HEADLINES} <= outs  # each is some stage's output


def test_figures_of_a_smoke_run_are_labelled_so(tmp_path):
    reports = _reports(tmp_path)
    (reports / "policy.json").write_text(json.dumps({"success_rate": {"source": 0.0, "expanded": 1.0},
                                                     "smoke_run": "smoke run (CPU default): not a result"}))
    write_summary(reports, reports / "headline.json", reports / "RESULTS.md")
    rows = {line.split(" | ")[0].strip("| "): line for line in (reports / "RESULTS.md").read_text().splitlines()}
    assert "| 1 | smoke run (CPU default): not a result |" in rows["policy success, expanded data"]
    assert "| 31 | measured |" in rows["generated episodes accepted"]
    assert "Smoke runs" in (reports / "RESULTS.md").read_text()
    assert json.loads((reports / "headline.json").read_text())["policy.success_rate_expanded"] == 1.0


def test_the_cpu_default_labels_its_smoke_runs_and_the_gpu_params_do_not():
    cpu, gpu = load_params(), load_params(file="params/gpu.yaml")
    label = {"smoke_run": "smoke run (CPU default): not a result"}
    assert [smoke_label(cpu, s) for s in ("policy_eval", "teacher_check", "train", "expand")] == [label, label, {}, {}]
    assert smoke_label(gpu, "policy_eval") == {} and smoke_label(gpu, "train_baselines") != {}
    with pytest.raises(ParamsError, match="smoke_run: stages: unknown stage 'policy'"):
        smoke_label(load_params("smoke_run.stages=[policy]"), "policy_eval")
