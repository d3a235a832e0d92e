"""benchmarks.rollout_speed end to end on CPU at tiny size: synthetic store, no Newton, ratios from a file."""

from __future__ import annotations

import json

import pytest
import torch

from benchmarks.model_speed import episode_model
from benchmarks.rollout_speed import main, time_projection
from tests.conftest import ROOT, load_params
from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.projection import TopologyProjection
from wc.train.config import TrainConfig
from wc.train.data import read_phase_window

TINY = ["--params", str(ROOT / "params.yaml"), "--set", "model.encoder_levels=1", "--set", "model.decoder_layers=1"]


@pytest.fixture(scope="module")
def store(synthetic_store) -> str:
    return str(synthetic_store(load_params(), [("fall", "test")], frames=6))


@pytest.mark.slow
def test_rollout_speed_runs_and_reports(tmp_path, store) -> None:
    reference = tmp_path / "sim_speed.json"
    reference.write_text(json.dumps({"settings": [
        {"bag_vertices": 300, "worlds": 1, "simulated_s_per_wall_s": 0.05, "simulated_s_per_wall_s_aggregate": 0.05},
        {"bag_vertices": 300, "worlds": 4, "simulated_s_per_wall_s": 0.02, "simulated_s_per_wall_s_aggregate": 0.08},
        {"bag_vertices": 20000, "worlds": 1, "simulated_s_per_wall_s": 9.0, "simulated_s_per_wall_s_aggregate": 9.0}]}))
    main([*TINY, "--store", store, "--frames", "4", "--repeats", "1", "--batches", "2", "--skins", "0.002,0.5",
          "--train-window", "3", "--train-steps", "1", "--profile-frames", "2", "--skip-newton",
          "--newton-reference", str(reference), "--out-dir", str(tmp_path), "--tag", "t"])
    report = json.loads((tmp_path / "rollout_speed_t.json").read_text())
    single = {r["variant"]: r for r in report["single"]}
    assert len(single) == 4 and all("ms_per_step_median" in r for r in single.values()), single
    projected = [name for name in single if name.endswith("+ topology projection P")]
    assert len(projected) == 1 and single[projected[0]]["finite"]  # the projection-stage rollout, timed apart
    projected_row = single.pop(projected[0])
    assert projected_row["simulated_s_per_wall_s"] > 0
    ref = single["fp32 reference"]
    for name, row in single.items():
        assert row["finite"] and row["position_mse_vs_fp32_reference_m2"] == 0.0, name  # reuse is exact
        assert row["simulated_s_per_wall_s"] > 0
    wide = single["fp32 + neighbour reuse, skin 500 mm"]
    assert wide["neighbour_searches"]["spatial"] == 1 and wide["neighbour_reuses"]["spatial"] == 3
    assert ref["neighbour_searches"] == "every step"
    assert {r["batch"] for r in report["batched"]} == {2} and all("ms_per_step_median" in r for r in report["batched"])
    assert "whole step" in report["other"]["profile"]["ms_per_step_median"]
    assert report["other"]["training"]["s_per_step_median"] > 0 and report["other"]["projection"]["ms"] > 0
    assert report["newton"] == []
    ratios = report["newton_for_ratios"]  # the closest vertex count of the reference file, marked as not this run
    assert ratios["single_s_per_s"] == 0.05 and ratios["multi_aggregate_s_per_s"] == 0.08
    assert "not this process" in ratios["source"]
    md = (tmp_path / "rollout_speed_t.md").read_text()
    assert "## Targets" in md and "fp32 + neighbour reuse, skin 2 mm" in md


def test_rollout_speed_budget_skips_rows(tmp_path, store) -> None:
    main([*TINY, "--store", store, "--frames", "2", "--repeats", "1", "--batches", "2", "--skins", "0.01", "--train-window", "0",
          "--profile-frames", "0", "--skip-newton", "--budget-s", "0", "--out-dir", str(tmp_path), "--tag", "b"])
    report = json.loads((tmp_path / "rollout_speed_b.json").read_text())
    rows = report["single"] + report["batched"]
    assert rows and all("skipped" in r["error"] for r in rows)


def test_the_projection_difference_is_the_rollout_call_against_the_eager_projection(store, monkeypatch) -> None:
    """The report's projection max_abs_difference_m: how far the projection as rollouts call it (forward, a replayed
    CUDA graph on CUDA) lands from the eager reference (project). On the CPU forward is project
    (tests/test_model_blocks.py), so a difference planted in forward alone must come out whole."""
    params = load_params("model.encoder_levels=1", "model.decoder_layers=1")
    trajectories, cpu = TrajectoryStore(store), torch.device("cpu")
    phase, model, layout = episode_model(trajectories, load_section(params, "model", ModelConfig), cpu)
    x = torch.from_numpy(read_phase_window(trajectories, phase, phase.start, 1)["x"])
    monkeypatch.setattr(TopologyProjection, "forward", lambda self, x_prev, x_pred: self.project(x_prev, x_pred) + 1e-3)
    measured = time_projection(model, layout, x, load_section(params, "train", TrainConfig), 1, cpu)
    assert measured["max_abs_difference_m"] == pytest.approx(1e-3, rel=1e-3)
