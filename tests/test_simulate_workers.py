"""Stage `simulate` with agent.workers: worker processes give the same store and memory as one process, and read an
earlier run's memory alike (agent.memory kept)."""

import json
from pathlib import Path

import numpy as np
import pytest
import warp as wp

from wc.agent.simulate_stage import simulate, task_key
from tests.conftest import load_params
from wc.agent.memory import FailureMemory, Outcome
from wc.config import ParamsError
from wc.data.store import TrajectoryStore

TWO_TASKS = ["agent.tasks=[bag_drop, sphere_drop]", "agent.episodes_per_task=1", "agent.max_attempts_per_task=2",
             "tasks.bag_drop.duration_s=0.2", "tasks.sphere_drop.duration_s=0.2", "sim.settle_s=0.1"]


def _run(tmp_path: Path, workers: int, overrides: tuple[str, ...] = ()) -> dict:
    params = load_params(*TWO_TASKS, f"agent.workers={workers}", *overrides)
    return simulate(params, tmp_path / "raw.zarr", tmp_path / "simulate.json", tmp_path / "memory.json")


def _seed_memory(path: Path) -> None:
    """An earlier run's failures in cell 0 of both tasks: the planners must read them (so pick cell 1)."""
    params = load_params(*TWO_TASKS)
    FailureMemory(path, [Outcome(name, task_key(params, name), 0, 0.1, 0.05, 1, "penetration", 3)
                         for name in ("bag_drop", "sphere_drop")]).save()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[int, tuple[Path, dict]]:
    out = {}
    for workers in (1, 2):
        path = tmp_path_factory.mktemp(f"workers{workers}")
        _seed_memory(path / "memory.json")
        out[workers] = path, _run(path, workers, ("agent.memory=kept",))  # the planners learn from the seeded file
    return out


@pytest.mark.slow
def test_workers_write_the_same_episodes(runs):
    (one, report_one), (two, report_two) = runs[1], runs[2]
    a, b = TrajectoryStore(one / "raw.zarr"), TrajectoryStore(two / "raw.zarr")
    assert a.attrs == b.attrs
    assert a.episode_ids == b.episode_ids and len(a.episode_ids) >= 2
    assert [a.episode_attrs(e)["task"] for e in a.episode_ids][0] == "bag_drop"  # task order, whoever finished first
    assert {a.episode_attrs(e)["cell"] for e in a.episode_ids} == {1}  # learnt from the seeded memory
    for eid in a.episode_ids:
        assert a.episode_attrs(eid) == b.episode_attrs(eid)
        ea, eb = a.read_episode(eid), b.read_episode(eid)
        for name in ("x", "v", "action", "link_poses", "env_poses"):
            np.testing.assert_array_equal(ea[name], eb[name], err_msg=f"{eid}/{name}")
    assert (report_one["workers"], report_two["workers"]) == (1, 2)
    assert report_one["params_hash"] == report_two["params_hash"]  # workers does not change the output
    for name, task in report_one["tasks"].items():  # counts and coverage; only the wall time may differ
        assert {**task, "wall_s": 0} == {**report_two["tasks"][name], "wall_s": 0}, name
    assert json.loads((two / "simulate.json").read_text())["workers"] == 2


@pytest.mark.slow
def test_workers_file_the_same_outcomes(runs):
    memories = [json.loads((runs[w][0] / "memory.json").read_text())["outcomes"] for w in (1, 2)]
    assert memories[0] == memories[1]
    assert [(o["task"], o["cell"]) for o in memories[0]][:3] == [("bag_drop", 0), ("sphere_drop", 0), ("bag_drop", 1)]
    assert memories[0][-1]["task"] == "sphere_drop"


@pytest.mark.slow
def test_a_fresh_run_ignores_the_memory_file_and_rewrites_it(tmp_path):
    """agent.memory fresh (the default): the seeded failures in cell 0 are not read, so the planners start in cell 0
    as a first run does, and the file keeps this run's outcomes alone."""
    _seed_memory(tmp_path / "memory.json")
    _run(tmp_path, 1)
    store = TrajectoryStore(tmp_path / "raw.zarr")
    assert {store.episode_attrs(e)["cell"] for e in store.episode_ids} == {0}
    outcomes = json.loads((tmp_path / "memory.json").read_text())["outcomes"]
    assert len(outcomes) == len(store.episode_ids)  # one per simulated episode (the raw store keeps rejected ones)
    assert [(o["task"], o["cell"]) for o in outcomes][:2] == [("bag_drop", 0), ("sphere_drop", 0)]


@pytest.mark.parametrize("workers, message", [(0, "workers must be >= 1, got 0"), (-2, "workers must be >= 1")])
def test_bad_workers_fail_without_output(tmp_path, workers, message):
    with pytest.raises(ParamsError, match=message):
        _run(tmp_path, workers)
    assert list(tmp_path.iterdir()) == []


def test_repeated_task_fails(tmp_path):
    params = load_params(*TWO_TASKS, "agent.tasks=[bag_drop, bag_drop]")
    with pytest.raises(ParamsError, match=r"tasks must not repeat, got \['bag_drop'\]"):
        simulate(params, tmp_path / "raw.zarr", tmp_path / "simulate.json", tmp_path / "memory.json")


@pytest.mark.slow
@pytest.mark.skipif(wp.is_cuda_available(), reason="needs a machine without CUDA to fail in the worker")
def test_worker_error_names_the_task_and_leaves_no_store(tmp_path):
    # the parent never builds a simulator, so sim.device=cuda without CUDA first fails in the worker
    with pytest.raises(RuntimeError, match=r"task 'sphere_drop' failed in a worker process: RuntimeError: "
                                           r"sim.device is 'cuda'"):
        _run(tmp_path, 2, ("agent.tasks=[sphere_drop]", "sim.device=cuda"))
    assert list(tmp_path.iterdir()) == []
