"""Stage `simulate`: a smoke run on the default params (shortened), and bad input that must fail cleanly."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from wc.agent.simulate_stage import simulate
from tests.conftest import ROOT, load_params
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.scene.config import SceneConfig
from wc.tasks.base import EpisodeSpec, get_task
from wc.validate.config import ValidateConfig
from wc.validate.predicates import first_failure
from wc.scene.episode_scenes import EpisodeScenes

SHORT = ["agent.tasks=[lift_handle]", "agent.episodes_per_task=1", "agent.max_attempts_per_task=1",
         "tasks.lift_handle.hold_s=0.2", "sim.settle_s=0.2"]


def _run(tmp_path: Path, overrides: list[str], out: Path | None = None):
    out = out or tmp_path / "raw.zarr"
    return simulate(load_params(*SHORT, *overrides), out, tmp_path / "simulate.json",
                    tmp_path / "memory.json")


def _no_output(tmp_path: Path) -> None:
    leftovers = [p.name for p in tmp_path.iterdir() if p.name not in ("blocker", "memory.json")]
    assert leftovers == [], f"partial output left behind: {leftovers}"


@pytest.mark.slow
def test_smoke_default_params(tmp_path):
    report = _run(tmp_path, [])
    store = TrajectoryStore(tmp_path / "raw.zarr")
    assert store.attrs["schema"] == "worldcontact-trajectories/1"
    assert store.dt == pytest.approx(0.04)
    assert store.object_names == ["bag"]
    assert len(store.link_names) == 16 and store.env_names == ["table"]
    assert {"right_finger_a", "left_link6", "table"} <= set(store.prescribed)
    (eid,) = store.episode_ids
    ep = store.read_episode(eid)
    frames = len(ep["x"])
    assert ep["x"].shape == (frames, store.num_vertices, 3) and ep["action"].shape == (frames, 14)
    assert ep["link_poses"].shape == (frames, 16, 7) and np.isfinite(ep["x"]).all()
    attrs = store.episode_attrs(eid)
    assert attrs["task"] == "lift_handle" and attrs["source"] == "simulator"
    # the verdict stored with the episode is the source checks', then the task's, on the stored arrays
    params = load_params(*SHORT)
    scene = EpisodeScenes(load_section(params, "scene", SceneConfig), store).scene(eid)
    verdict = first_failure(scene, ep["x"], ep["v"], ep["action"], ep["link_poses"],
                            load_section(params, "validate", ValidateConfig), frame_dt_s=store.dt)
    if verdict is None:
        spec = EpisodeSpec(attrs["task"], attrs["seed"], attrs["cell"], attrs["speed"], attrs["amplitude"])
        reason = get_task(attrs["task"], params).check(scene, spec, ep["x"], ep["action"])
        verdict = (reason, len(ep["x"]) - 1) if reason else None
    assert (attrs["first_failure"], attrs["failure_frame"]) == (verdict or (None, None))
    assert attrs["accepted"] is (verdict is None)
    written = json.loads((tmp_path / "simulate.json").read_text())
    assert written == json.loads(json.dumps(report, default=float))
    assert written["episodes"] == 1 and written["frames"] == frames
    assert written["solver_steps"] > 0 and written["simulated_s_per_wall_s"] > 0
    assert written["params_hash"] == store.attrs["params_hash"]
    assert written["tasks"]["lift_handle"]["cells_visited"] == 1
    memory = json.loads((tmp_path / "memory.json").read_text())["outcomes"]
    assert [(o["task"], o["failure"]) for o in memory] == [("lift_handle", attrs["first_failure"])]
    assert attrs["objects"] == ["bag"] and attrs["links"] == store.link_names


@pytest.mark.parametrize("overrides, message", [
    (["agent.tasks=[fold_shirt]"], "unknown task 'fold_shirt'"),
    (["scene.bag.target_vertices=0"], "target_vertices must be positive"),
    (["sim.substeps=0"], "substeps must be >= 1"),
])
def test_bad_params_fail_without_output(tmp_path, overrides, message):
    with pytest.raises((ParamsError, ValueError), match=message):
        _run(tmp_path, overrides)
    _no_output(tmp_path)


def test_missing_params_key_fails_without_output(tmp_path):
    params = load_params(*SHORT)
    del params["sim"]["dt_s"]
    with pytest.raises(ParamsError, match=r"missing key sim\.dt_s"):
        simulate(params, tmp_path / "raw.zarr", tmp_path / "simulate.json", tmp_path / "memory.json")
    _no_output(tmp_path)


def test_unwritable_output_fails_without_output(tmp_path):
    (tmp_path / "blocker").write_text("a file where a directory should be")
    with pytest.raises(OSError, match="blocker"):
        _run(tmp_path, [], out=tmp_path / "blocker" / "raw.zarr")
    _no_output(tmp_path)


@pytest.mark.slow
def test_dvc_pipeline_declares_simulate():
    listed = subprocess.run([sys.executable, "-m", "dvc", "stage", "list"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout
    assert "simulate" in listed and "raw.zarr" in listed


@pytest.mark.parametrize("key", ["body_particle_contact_buffer", "body_contact_buffer"])
def test_bad_contact_buffer_fails_without_output(tmp_path, key):
    params = load_params(*SHORT)
    params["sim"][key] = 0
    with pytest.raises(ValueError, match=f"{key} must be >= 1"):
        simulate(params, tmp_path / "raw.zarr", tmp_path / "simulate.json", tmp_path / "memory.json")
    _no_output(tmp_path)


@pytest.mark.slow
def test_deadline_passed_keeps_a_valid_store(tmp_path):
    """A chunked job whose time is up starts no batch: the report says so and the store is still whole."""
    report = simulate(load_params(*SHORT), tmp_path / "raw.zarr", tmp_path / "simulate.json",
                      tmp_path / "memory.json", max_minutes=1e-9)
    assert report["stopped_early"] is True and report["episodes"] == 0
    assert TrajectoryStore(tmp_path / "raw.zarr").episode_ids == []


@pytest.mark.slow
def test_several_worlds_fill_every_batch(tmp_path):
    """With 2 worlds a task wanting 1 episode still simulates a full batch of 2 (an idle world costs as much)."""
    report = _run(tmp_path, ["sim.worlds=2", "agent.max_attempts_per_task=2"])
    assert report["episodes"] == 2 and report["stopped_early"] is False
    store = TrajectoryStore(tmp_path / "raw.zarr")
    assert len(store.episode_ids) == 2
    seeds = [store.episode_attrs(e)["seed"] for e in store.episode_ids]
    assert len(set(seeds)) == 2
