"""The ray executor in the three data stages, on a Ray instance of two CPUs started here: simulate, expand and render
write the same stores (and simulate the same failure memory) as the local executor, with two batches of one task in
flight where they can finish out of order; a render unit that keeps failing is logged and listed in the report, and
no rendered store is written."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import SyntheticStore, load_params
from tests.expand_inputs import expand_params, write_source_store, write_tiny_model
from tests.flaky_units import BAD_EPISODE, FailingRenderWorker
from tests.test_simulate_workers import TWO_TASKS
from wc.agent.simulate_stage import simulate
from wc.data.store import TrajectoryStore
from wc.distributed import UnitsFailed
from wc.expand import expand
from wc.render import stage as render_stage
from wc.render.frames import RenderedStore

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("local_ray")]
TIMING = {"wall_s", "episodes_per_min", "solver_steps_per_s", "simulated_s_per_wall_s", "rollout_s",
          "model_frames_per_s", "trajectories_per_min", "accepted_per_min", "ms_per_frame",
          "ms_per_frame_all_cameras_wall", "renderers_built", "executor", "out", "rejected_out", "outputs",
          "contact_sheet", "memory"}


def _same_stores(a: Path, b: Path) -> list[str]:
    """The episode ids of trajectory stores `a` and `b`, after checking their attrs and arrays are equal."""
    sa, sb = TrajectoryStore(a), TrajectoryStore(b)
    assert sa.attrs == sb.attrs and sa.episode_ids == sb.episode_ids
    for eid in sa.episode_ids:
        assert sa.episode_attrs(eid) == sb.episode_attrs(eid), eid
        ea, eb = sa.read_episode(eid), sb.read_episode(eid)
        for name in ea:
            np.testing.assert_array_equal(ea[name], eb[name], err_msg=f"{eid}/{name}")
    return sa.episode_ids


def _same_reports(a: dict[str, Any], b: dict[str, Any], other: str = "ray") -> None:
    """Equal but for timings, output paths and where the work ran."""
    def kept(r: dict[str, Any]) -> dict[str, Any]:
        tasks = {name: {**t, "wall_s": None} for name, t in r.get("tasks", {}).items()}
        return {k: v for k, v in r.items() if k not in TIMING} | ({"tasks": tasks} if tasks else {})

    assert kept(a) == kept(b)
    assert (a["executor"]["name"], b["executor"]["name"]) == ("local", other)
    assert b["executor"].get("failed_units", []) == []


@pytest.mark.parametrize("in_flight", [1, 2])
def test_simulate_writes_the_same_episodes_and_memory_on_ray(tmp_path, in_flight):
    runs = {}
    for executor in ("local", "ray"):
        params = load_params(*TWO_TASKS, "agent.episodes_per_task=2", "agent.max_attempts_per_task=3",
                             "agent.workers=1", f"agent.executor={executor}", f"agent.batches_in_flight={in_flight}")
        d = tmp_path / executor
        runs[executor] = d, simulate(params, d / "raw.zarr", d / "simulate.json", d / "memory.json")
    (local, a), (ray, b) = runs["local"], runs["ray"]
    assert len(_same_stores(local / "raw.zarr", ray / "raw.zarr")) >= 4
    memories = [json.loads((d / "memory.json").read_text())["outcomes"] for d in (local, ray)]
    assert memories[0] == memories[1] and [o["task"] for o in memories[0]][0] == "bag_drop"  # filed in task order
    _same_reports(a, b)
    assert [t["wall_s"] > 0 for t in b["tasks"].values()] == [True, True]
    assert b["executor"]["units"] == sum(t["episodes"] for t in b["tasks"].values())  # sim.worlds 1: one per unit


def test_expand_writes_the_same_episodes_on_ray(tmp_path):
    params = expand_params()
    params["expand"].update(engine="batches",  # the Ray executor runs the reference engine's batches as its units
                            batch_size=1, batches_in_flight=2, max_attempts=4, untangle="rollback", self_contact=False,
                            projection_iterations=5, projection_final_edge_passes=0)
    store, model = write_source_store(tmp_path, params), write_tiny_model(tmp_path, params)
    runs = {}
    for executor in ("local", "ray"):
        params["expand"]["executor"] = executor
        d = tmp_path / executor
        runs[executor] = expand(params, model, store, d / "e.zarr", d / "e.json", d / "rejected.zarr")
    assert len(_same_stores(tmp_path / "local/e.zarr", tmp_path / "ray/e.zarr")) == runs["local"]["accepted"] == 2
    _same_stores(tmp_path / "local/rejected.zarr", tmp_path / "ray/rejected.zarr")
    _same_reports(runs["local"], runs["ray"])
    assert runs["ray"]["projection_stats"]["steps"] > 0 and "rolled_back_vertex_steps" in runs["ray"]["untangle_stats"]
    assert runs["ray"]["executor"]["units"] == 2


@pytest.fixture(scope="module")
def render_inputs(synthetic_store: SyntheticStore) -> tuple[dict[str, Any], Path]:
    params = load_params()
    params["render"].update(width=32, height=32, frames_per_batch=4, tasks=None, sheet_frames=3, episodes_per_unit=1)
    return params, synthetic_store(params, [("carry", "train"), ("fall", "train"), ("handoff", "test")], frames=5)


@pytest.mark.parametrize("other", ["ray", "processes"])
def test_render_writes_the_same_frames_on_ray_or_device_processes(tmp_path, render_inputs, other):
    params, store = render_inputs
    runs = {}
    for executor in ("local", other):
        params["render"]["executor"] = executor
        d = tmp_path / executor
        runs[executor] = render_stage.render(params, [(store, d / "r.zarr")], d / "r.json", d / "sheet.png")
    a, b = RenderedStore(tmp_path / "local/r.zarr"), RenderedStore(tmp_path / other / "r.zarr")
    assert a.episode_ids() == b.episode_ids() == TrajectoryStore(store).episode_ids and a.attrs == b.attrs
    for eid in a.episode_ids():
        assert a.episode_attrs(eid) == b.episode_attrs(eid)
        for camera in a.cameras:
            np.testing.assert_array_equal(a.frames(eid, camera), b.frames(eid, camera), err_msg=f"{eid}/{camera}")
    _same_reports(runs["local"], runs[other], other)
    assert runs[other]["executor"]["units"] == 3 and (tmp_path / other / "sheet.png").is_file()


def test_a_render_unit_that_keeps_failing_leaves_no_store(tmp_path, render_inputs, monkeypatch, caplog):
    params, store = render_inputs
    params["render"]["executor"] = "ray"
    params["ray"]["max_retries"] = 1
    monkeypatch.setattr(render_stage, "RenderWorker", FailingRenderWorker)
    with caplog.at_level(logging.ERROR, logger="wc.distributed.executors"), \
            pytest.raises(UnitsFailed, match=f"render: 1 work unit.* kept failing .*{BAD_EPISODE}"):
        render_stage.render(params, [(store, tmp_path / "r.zarr")], tmp_path / "r.json", tmp_path / "sheet.png")
    assert not (tmp_path / "r.zarr").exists() and not (tmp_path / "sheet.png").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temporary left behind either
    report = json.loads((tmp_path / "r.json").read_text())
    [failed] = report["executor"]["failed_units"]
    assert BAD_EPISODE in failed["label"]
    assert failed["error"] == f"RuntimeError: injected failure rendering {BAD_EPISODE}"
    assert f"episodes {BAD_EPISODE}..{BAD_EPISODE} kept failing (2 tries)" in caplog.text
    assert report["outputs"] == [] and report["episodes"] == 0
