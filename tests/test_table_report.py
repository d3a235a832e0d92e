"""The Table-1 report (wc.eval.table_report): ratios to the best baseline, the paper's figures beside, training
budgets read from both report shapes, batched speed rows at their method's accuracy, the margin verdict, the chart."""

from __future__ import annotations

import json

import pytest

from wc.eval.table_report import PAPER_TABLE1, batched_rows, main, method_kinds, training_rows

TASKS = ("lift", "shake")


def _method(mse: float, pen: float = 0.0, s_per_step: float = 0.02) -> dict:
    return {"position_mse_m2": mse, "velocity_mse_m2_s2": 10 * mse, "penetration_rate_pct": pen,
            "contact_penetration_rate_pct": 2 * pen, "s_per_step": s_per_step,
            "per_task": {t: {"position_mse_m2": mse * (i + 1)} for i, t in enumerate(TASKS)}}


def _stability(diverged: int, steps: list[int | None]) -> dict:
    return {"diverged": diverged, "rollouts": len(steps),
            "first_divergence_step": {f"lift/ep_{i}@0": s for i, s in enumerate(steps)}}


@pytest.fixture
def metrics() -> dict:
    methods = {"worldcontact": _method(1e-5), "robocraft": _method(2e-4, s_per_step=0.01),
               "adaptigraph": _method(1.5e-4, pen=0.5), "zero_motion": _method(3e-4, s_per_step=1e-5)}
    chart = {**methods, "newton_reference": _method(5e-6, s_per_step=0.04)}
    return {"methods": methods, "environment": {"gpu": "TestGPU", "torch": "t", "warp": "w", "newton": "n"},
            "held_out": {"rollouts": 4, "rollout_frames": 25, "source": "test split"},
            "stability": {"stability_frames": 100, "source": "test split",
                          "methods": {"worldcontact": _stability(0, [None, None]),
                                      "robocraft": _stability(2, [40, 60])}},
            "speed_accuracy": {"rollouts": 2, "methods": chart, "newton": {"newton_reference": {"iterations": 5}}},
            "ground_truth": {"penetration_rate_pct": 0.0, "contact_penetration_rate_pct": 0.0}, "dt": 0.04}


@pytest.fixture
def speed() -> dict:
    return {"dt": 0.04,
            "batched": [{"variant": "bf16", "batch": 32, "bf16": True, "simulated_s_per_wall_s_aggregate": 60.0},
                        {"variant": "bf16 + reuse, skin 2 mm", "batch": 32, "bf16": True,
                         "simulated_s_per_wall_s_aggregate": 70.0}],
            "newton": [{"worlds": 1, "simulated_s_per_wall_s_aggregate": 1.0},
                       {"worlds": 32, "simulated_s_per_wall_s_aggregate": 20.0}]}


def test_report_has_ratios_paper_figures_budgets_speed_and_verdict(tmp_path, metrics, speed):
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    (tmp_path / "speed.json").write_text(json.dumps(speed))
    runs = tmp_path / "runs"
    runs.mkdir()
    (runs / "train_worldcontact.json").write_text(json.dumps(
        {"steps": {"base": 300, "projection": 60}, "wall_s": 120.0, "s_per_step_median": 0.3, "best_val_loss": 2.5}))
    (runs / "train_baseline_robocraft.json").write_text(json.dumps({"baselines": {"robocraft": {
        "steps_done": 900, "wall_s": 125.0, "s_per_step_median": 0.1, "stopped_by": "converged",
        "best_val_loss": 0.01}}}))
    main(["--metrics", str(tmp_path / "metrics.json"), "--trainings", str(runs), "--speed", str(tmp_path / "speed.json"),
          "--out", str(tmp_path / "t.md"), "--chart", str(tmp_path / "chart.png")])
    text = (tmp_path / "t.md").read_text()
    table1 = text.split("## Position MSE")[0]
    rows = {line.split(" | ")[0].strip("| "): line for line in table1.splitlines() if line.startswith("| ")}
    assert "| 15.0 |" in rows["worldcontact"]  # best baseline adaptigraph 1.5e-4 / 1e-5
    assert "0.0002 / 0.0002, 0.35" in rows["worldcontact"] and "0.0598" in rows["robocraft"]
    assert "| 2/2 |" in rows["robocraft"] and "| robocraft | 2/2 | 50 |" in text  # median of steps 40 and 60
    assert "| worldcontact | 360 | 2.0 |" in text and "| robocraft | 900 | 2.1 | 0.100 | converged |" in text
    assert "worldcontact B=32 (batched, aggregate) | 60 |" in text and "skin" not in text
    assert "newton_reference 32 worlds (batched, aggregate) | 20 |" in text
    assert "15.0x below the best baseline (adaptigraph); goal >= 10x: met" in text
    assert "penetration 0.00 %; goal <= 0.35 %: met" in text
    assert (tmp_path / "chart.png").stat().st_size > 10_000
    assert set(PAPER_TABLE1) == {"robocraft", "robocook", "adaptigraph", "worldcontact"}


def test_kinds_and_batched_points(metrics, speed):
    kinds = method_kinds(metrics)
    assert kinds == {"worldcontact": "worldcontact", "robocraft": "baseline", "adaptigraph": "baseline",
                     "zero_motion": "zero_motion", "newton_reference": "newton"}
    assert method_kinds({**metrics, "kinds": {"a": "baseline"}}) == {"a": "baseline"}
    rows = batched_rows(speed, metrics["speed_accuracy"]["methods"], kinds)
    assert [r[0] for r in rows] == ["worldcontact B=32", "newton_reference 32 worlds"]
    assert rows[0][3] == 1e-5 and rows[1][3] == 5e-6  # each at its single method's accuracy


def test_missing_dt_is_named(tmp_path, metrics):
    del metrics["dt"]
    (tmp_path / "m.json").write_text(json.dumps(metrics))
    with pytest.raises(ValueError, match="frame dt"):
        main(["--metrics", str(tmp_path / "m.json"), "--out", str(tmp_path / "t.md")])


def test_training_rows_skip_unknown_reports(tmp_path):
    (tmp_path / "train_other.json").write_text(json.dumps({"steps": 5}))
    assert training_rows(tmp_path) == {}


def test_report_shows_the_whole_episode_ratios_and_the_phases(tmp_path, metrics):
    metrics["held_out"]["episode_frames"] = 250
    metrics["whole_episode"] = {
        "subject": "worldcontact", "baselines": ["robocraft", "zero_motion"], "rollouts": 6, "mean_task_ratio": 8.5,
        "worst_task_ratio": 0.8, "pooled_ratio": 20.6, "penetration_pct": 0.2,
        "per_task": {"grasp": {"ratio": 16.2, "best_baseline": "zero_motion", "best_baseline_mse_m2": 3.2e-3,
                               "subject_mse_m2": 2e-4},
                     "lift": {"ratio": 0.8, "best_baseline": "robocraft", "best_baseline_mse_m2": 1.6e-5,
                              "subject_mse_m2": 2e-5}}}
    for i, m in enumerate(metrics["methods"].values()):
        m["per_phase"] = {"approach": {"position_mse_m2": 1e-6 * (i + 1)}, "lift": {"position_mse_m2": 1e-5 * (i + 1)}}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    main(["--metrics", str(tmp_path / "metrics.json"), "--out", str(tmp_path / "t.md")])
    text = (tmp_path / "t.md").read_text()
    assert "has 8.5x its position MSE as the mean over tasks of per-task ratios (goal >= 10x: not met)" in text
    assert "0.80x on the worst task, 20.6x pooled over tasks" in text
    assert "| lift | robocraft | 1.60e-05 | 2.00e-05 | 0.80 |" in text  # a task a baseline wins is shown
    assert "| robocraft | 2.00e-06 | 2.00e-05 |" in text.split("per motion phase")[1]
    assert "Map-back floor" not in text  # no particle baseline's floor measured: no section
    metrics["map_back"] = {"robocraft": {"position_mse_m2": 5e-5, "per_task": {},
                                         "layouts": [{"particles": 100, "vertices": 306}]}}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    main(["--metrics", str(tmp_path / "metrics.json"), "--out", str(tmp_path / "t.md")])
    assert "| robocraft | 100 / 306 | 5.00e-05 | 2.00e-04 | 25.0 % |" in (tmp_path / "t.md").read_text()
    del metrics["whole_episode"]  # a report from before whole episodes: no section
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    main(["--metrics", str(tmp_path / "metrics.json"), "--out", str(tmp_path / "t.md")])
    assert "Whole held-out episodes" not in (tmp_path / "t.md").read_text()
