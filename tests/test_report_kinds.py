"""The results page's GPU headlines (wc/report_kinds.py, wc/results_page.py): every committed GPU report has a
declared kind and every field its kind's headline reads; a missing field or an undeclared report stops the summary;
the page leads with the headline figures."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.conftest import ROOT
from wc.report_kinds import HeadlineError, field_value, kind_of, report_headline
from wc.results_page import FEATURED, smoke_label
from wc.summary import write_summary

GPU = ROOT / "reports" / "gpu"


@pytest.mark.parametrize("name", sorted(p.name for p in GPU.glob("*.json")))
def test_every_committed_gpu_report_has_its_kinds_headline_fields(name: str) -> None:
    kind, line = report_headline(GPU / name)
    assert kind == kind_of(name).name and line


def test_wildcards_read_every_key_or_item_and_a_missing_part_is_a_key_error() -> None:
    data = {"arms": {"a": {"n": 1}, "b": {"n": 2}}, "rows": [{"w": 1}, {"w": 4}], "empty": {}}
    assert field_value(data, "arms.*.n") == {"a": 1, "b": 2} and field_value(data, "rows.*.w") == {0: 1, 1: 4}
    assert field_value(data, "rows.1.w") == 4
    for path in ("arms.*.m", "empty.*", "arms.c", "rows.2.w"):
        with pytest.raises(KeyError):
            field_value(data, path)


def test_headlines_give_the_figures_of_the_committed_runs() -> None:
    _, policy = report_headline(GPU / "policy_h100_three_arms.json")
    assert policy.startswith("source 37/50 (0.60-0.84), expanded 45/50 (0.79-0.96), newton_150 48/50 (0.87-0.99)")
    assert "50 closed-loop Newton trials per policy on the same seeds" in policy and "3e36c8740e1d2286" in policy
    _, table1 = report_headline(GPU / "metrics_h100_table1_solo.json")
    assert "vs best baseline robocook 0.000869: 20.6x lower" in table1 and "lower on 6 of 6 tasks" in table1
    _, expand = report_headline(GPU / "expand_h100_lift_handle_25to150.json")
    assert expand.startswith("125 of 125 generated episodes accepted (acceptance 1.00), 19.3 accepted per minute")


def test_a_missing_headline_field_or_an_undeclared_report_stops_the_summary(tmp_path: Path) -> None:
    reports = tmp_path / "reports"
    (reports / "gpu").mkdir(parents=True)
    data = json.loads((GPU / "expand_h100_lift_handle_25to150.json").read_text())
    del data["accepted_per_min"]
    (reports / "gpu" / "expand_h100_x.json").write_text(json.dumps(data))
    with pytest.raises(HeadlineError, match="expand_h100_x.json: a 'expansion' report without its headline field "
                                            "'accepted_per_min'"):
        write_summary(reports, reports / "headline.json", reports / "RESULTS.md")
    assert not (reports / "headline.json").exists() and not (reports / "RESULTS.md").exists()
    (reports / "gpu" / "expand_h100_x.json").unlink()
    (reports / "gpu" / "mystery_h100.json").write_text("{}")
    with pytest.raises(HeadlineError, match="mystery_h100.json: no report kind matches"):
        write_summary(reports, reports / "headline.json", reports / "RESULTS.md")


def test_the_page_leads_with_the_featured_headlines(tmp_path: Path) -> None:
    for f in FEATURED:
        assert (GPU / f.report).is_file() and (ROOT / "reports" / f.write_up).is_file(), f
    reports = tmp_path / "reports"
    shutil.copytree(GPU, reports / "gpu")
    write_summary(reports, reports / "headline.json", reports / "RESULTS.md")
    first_screen = "\n".join((reports / "RESULTS.md").read_text().splitlines()[:12])
    assert "source 37/50" in first_screen and "20.6x lower" in first_screen and "125 of 125" in first_screen
    assert (ROOT / "reports" / "RESULTS.md").read_text().splitlines()[:12] == first_screen.splitlines()


def test_few_trials_are_labelled_a_smoke_run() -> None:
    assert smoke_label({"trials": 1}).startswith("**A smoke run**")
    assert "smoke" not in smoke_label({"trials": 50}) and "no policy evaluation" in smoke_label(None)


def test_data_generation_scaling_has_a_headline_per_stage_and_gpu_count() -> None:
    rows = [{"gpus": 1, "stage": "simulate", "episodes_per_min": 40.0, "speedup": 1.0},
            {"gpus": 2, "stage": "simulate", "episodes_per_min": 76.0, "speedup": 1.9}]
    report = {"rows": rows, "environment": {"gpu": "2 x NVIDIA H200"}}
    line = kind_of("generate_scaling_h200x2.json").headline(report, "generate_scaling_h200x2.json")
    assert line.endswith("simulate on 1 GPU(s): 40 episodes/min (1x); simulate on 2 GPU(s): 76 episodes/min (1.9x)")
    without = {**report, "rows": [{k: v for k, v in rows[0].items() if k != "speedup"}]}
    with pytest.raises(HeadlineError, match="speedup"):
        kind_of("generate_scaling_h200x2.json").headline(without, "generate_scaling_h200x2.json")


def test_policy_schedules_are_not_read_as_a_policy_evaluation() -> None:
    rows = [{"schedule": "one_after_another", "wall_s": 128.3, "speedup": 1.0},
            {"schedule": "side_by_side", "wall_s": 86.2, "speedup": 1.49}]
    report = {"rows": rows, "policy_type": "act", "environment": {"gpu": "2 x NVIDIA H200"}}
    kind = kind_of("policy_placement_h200x2.json")
    assert kind.name == "policy training schedules" and kind_of("policy_h100_x.json").name == "policy evaluation"
    assert kind.headline(report, "policy_placement_h200x2.json").endswith(
        "one after another 128 s (1x); side by side 86.2 s (1.5x)")
