"""benchmarks/generate_scaling.py: its speedups (per stage, against 1 device of the same run), its params (the same
work for every K) and, slow, a smoke run on CPU processes at the smallest size."""

from __future__ import annotations

import argparse
import json

import pytest
import yaml

from benchmarks import generate_scaling as bench
from tests.conftest import ROOT
from tests.expand_inputs import expand_params, write_source_store, write_tiny_model
from wc.agent.runner import AgentConfig
from wc.config import load_section
from wc.distributed import ProcessesConfig
from wc.expand import ExpandConfig


def test_speedups_are_against_one_device_of_the_same_stage():
    rows = [{"gpus": 1, "stage": "simulate", "episodes_per_min": 2.0}, {"gpus": 1, "stage": "expand",
                                                                        "episodes_per_min": 10.0},
            {"gpus": 2, "stage": "simulate", "episodes_per_min": 3.0}, {"gpus": 2, "stage": "expand",
                                                                        "episodes_per_min": 19.0}]
    assert [r["speedup"] for r in bench.with_speedups(rows)] == [1.0, 1.0, 1.5, 1.9]
    assert bench.with_speedups([{"gpus": 2, "stage": "expand", "episodes_per_min": 1.0}])[0]["speedup"] is None
    repeat = {"gpus": 1, "stage": "expand", "episodes_per_min": 5.0, "repeat": True}  # a control, not the base
    assert [r["speedup"] for r in bench.with_speedups([*rows, repeat])] == [1.0, 1.0, 1.5, 1.9, 0.5]


def test_every_k_does_the_same_work(tmp_path):
    params = expand_params()
    store = write_source_store(tmp_path, params)
    args = argparse.Namespace(params=ROOT / "params.yaml", task="lift_handle", episodes=3, in_flight=2, store=store,
                              overrides=["expand.max_sources=1"])
    one, two = (bench.stage_params(args, k, [1, 2]) for k in (1, 2))
    assert {k: v for k, v in one.items() if k != "processes"} == {k: v for k, v in two.items() if k != "processes"}
    agent, expand = load_section(two, "agent", AgentConfig), load_section(two, "expand", ExpandConfig)
    assert (agent.executor, agent.batches_in_flight, agent.episodes_per_task) == ("processes", 4, 3)
    assert (expand.shards, expand.target_trajectories) == (2, 1 + 3)  # one source episode + the generated ones
    assert load_section(two, "processes", ProcessesConfig).devices == 2


@pytest.mark.slow
def test_a_cpu_smoke_run_writes_rows_for_both_stages(tmp_path):
    params = expand_params()  # the expand tests' loose checks and short lift_handle programs
    store, model = write_source_store(tmp_path, params), write_tiny_model(tmp_path, params)
    file = tmp_path / "params.yaml"
    file.write_text(yaml.safe_dump({k: v for k, v in params.items() if not k.startswith("_")}))
    report = bench.main(["--params", str(file), "--devices", "1,2", "--episodes", "1", "--task", "bag_drop",
                         "--store", str(store), "--model", str(model), "--out-dir", str(tmp_path / "out"),
                         "--tag", "smoke", "--set", "tasks.bag_drop.duration_s=0.2", "--set", "sim.settle_s=0.1",
                         "--repeat-first"])
    repeats, rows = report["rows"][2:4], report["rows"][:2] + report["rows"][4:]
    assert [(r["gpus"], r["stage"], r["repeat"]) for r in repeats] == [(1, "simulate", True), (1, "expand", True)]
    assert all(r["same_as_first"]["identical_episodes"] == r["same_as_first"]["episodes"] >= 1 for r in repeats)
    assert "| 1 (repeat) | simulate |" in (tmp_path / "out" / "generate_scaling_smoke.md").read_text()
    assert [(r["gpus"], r["stage"]) for r in rows] == [(1, "simulate"), (1, "expand"), (2, "simulate"), (2, "expand")]
    assert all(r["wall_s"] >= r["stage_wall_s"] > 0 and r["episodes"] >= 1 for r in rows)
    for row in (r for r in rows if r["stage"] == "expand"):  # each shard's own time, inside the stage's
        assert len(row["shards"]) == 2 and all(0 < s["wall_s"] <= row["stage_wall_s"] for s in row["shards"])
    assert [r["executor"]["devices"] for r in rows if r["stage"] == "expand"] == [["cpu"], ["cpu", "cpu"]]
    assert rows[0]["speedup"] == 1.0 and rows[2]["speedup"] > 0
    for row in rows[2:]:  # the same work on two CPU processes: the same stores as on one
        same = row["same_as_first"]
        assert same["same_verdicts"] and same["identical_episodes"] == same["episodes"] >= 1, same
        assert same["max_position_diff_m"] == 0.0
    assert (tmp_path / "out/generate_scaling_smoke.md").read_text().startswith("# Data generation scaling (smoke)")
    assert json.loads((tmp_path / "out/generate_scaling_smoke.json").read_text())["shards"] == 2
