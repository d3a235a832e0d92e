"""Stage `expand` on a synthetic store with a tiny untrained WorldContact: rigid initial-state transforms,
the simulator's frame-0 posture (planned on the state before settling), infeasible plans that penetrate at
frame 0, parents of the same cell, batched rollouts that survive a diverged member, contact-projected
schema-valid output, per-check rejection counts, determinism and clear errors."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml

from stages.expand import main
from tests.conftest import load_params
from tests.expand_inputs import TASK, expand_params, write_source_store, write_tiny_model
from tests.synthetic_store import write_synthetic_store
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.dynamics import ObjectState
from wc.expand import (ExpandConfig, NoSourceEpisodesError, SourceEpisode, check_clear_at_start, check_on_table,
                       expand, pick_parent, plan_episode, planar_transform, presettle_state)
from wc.model.learned_dynamics import finite_rollout
from wc.model.projection import edges_from_faces
from wc.model_ref import file_sha256
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.tasks.base import EpisodeSpec, InfeasibleEpisode, get_task
from wc.validate import PREDICATES
from wc.validate.config import ValidateConfig
from wc.validate.predicates import cloth_rows, robot_boxes, table_and_robot_distance


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    return expand_params()


@pytest.fixture(scope="module")
def store_path(tmp_path_factory, params) -> Path:
    return write_source_store(tmp_path_factory.mktemp("store"), params)


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory, params) -> Path:
    return write_tiny_model(tmp_path_factory.mktemp("models"), params)


@pytest.fixture(scope="module")
def run(tmp_path_factory, params, store_path, model_dir) -> tuple[Path, dict[str, Any]]:
    d = tmp_path_factory.mktemp("out")
    return d, expand(params, model_dir, store_path, d / "expanded.zarr", d / "expand.json")


def _edge_lengths(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    e = edges_from_faces(torch.from_numpy(faces.astype(np.int64))).numpy()
    return np.linalg.norm(x[..., e[:, 0], :] - x[..., e[:, 1], :], axis=-1)


def test_planar_transform_is_rigid_and_keeps_the_bag_on_the_table(params):
    scene = build_scene(load_section(params, "scene", SceneConfig), ["bag"])
    bag = scene.objects["bag"]
    x = bag.vertices + np.float32([0.01, -0.02, 0.004])
    y = planar_transform(x, 35.0, (0.03, -0.01))
    assert _edge_lengths(y, bag.faces) == pytest.approx(_edge_lengths(x, bag.faces), abs=1e-6)
    assert np.array_equal(y[:, 2], x[:, 2]) and y[:, 2].min() >= scene.table.top_z
    assert y[:, :2].mean(0) == pytest.approx(x[:, :2].mean(0) + [0.03, -0.01], abs=1e-6)
    rel_x, rel_y = x[:, :2] - x[:, :2].mean(0), y[:, :2] - y[:, :2].mean(0)
    angle = np.arctan2(rel_y[:, 1], rel_y[:, 0]) - np.arctan2(rel_x[:, 1], rel_x[:, 0])
    far = np.linalg.norm(rel_x, axis=1) > 0.01
    assert np.rad2deg(np.angle(np.exp(1j * angle[far]))) == pytest.approx(35.0, abs=1e-3)
    check_on_table(y, scene.table)
    with pytest.raises(InfeasibleEpisode, match="sampled region"):
        check_on_table(planar_transform(x, 0.0, (0.3, 0.0)), scene.table)


class _StubPredictor:
    """x += 1 per step, stopping the whole batch at the first non-finite member (as WorldContact does);
    member 0 turns NaN at its 3rd step."""

    def rollout(self, layout, x0, v0, poses, dt):
        steps = poses.shape[1] - 1
        xs = torch.full((x0.shape[0], steps, *x0.shape[1:]), float("nan"))
        x = x0.clone()
        for t in range(steps):
            x = x + 1.0
            if self.poison and t == 2:
                x[0] = float("nan")
            xs[:, t] = x
            if not torch.isfinite(x).all():
                break
        self.poison = False
        return xs, torch.zeros_like(xs).masked_fill(xs.isnan(), float("nan"))

    poison = True


def test_a_diverged_member_does_not_cut_the_batch_short():
    x0 = np.zeros((3, 4, 3), np.float32)
    x, v = finite_rollout(_StubPredictor(), None, x0, x0, np.zeros((3, 8, 2, 7), np.float32), 0.04, torch.device("cpu"))
    assert x.shape == (3, 8, 4, 3)
    assert np.isfinite(x[0, :3]).all() and np.isnan(x[0, 3:]).all()  # diverged at frame 3, NaN from there
    for b in (1, 2):
        assert x[b, :, 0, 0] == pytest.approx(np.arange(8))  # finished, as if never batched with member 0


@pytest.mark.slow
def test_stage_writes_checked_worldcontact_episodes(run, store_path, params, model_dir):
    out, r = run
    assert json.loads((out / "expand.json").read_text()) == json.loads(json.dumps(r))
    assert r["source_episodes"] == 2 and r["wanted_generated"] == 2
    assert r["accepted"] == 2 and r["target_reached"] and r["expanded_total"] == 4
    assert r["generated"] == r["accepted"] + sum(r["rejections"].values())
    assert set(PREDICATES) <= set(r["rejections"]) and r["trajectories_per_min"] > 0 and r["device"] == "cpu"
    assert r["projection"] == "joint" and r["projection_stats"]["steps"] > 0  # the params default
    assert [s["presettle_state"] for s in r["sources"]] == [False, False]  # synthetic: not the agent's frame 0
    weights = file_sha256(Path(model_dir) / "model.safetensors")
    assert r["model"]["path"] == str(model_dir) and r["model"]["sha256"] == weights
    src, dst = TrajectoryStore(store_path), TrajectoryStore(out / "expanded.zarr")
    assert dst.attrs["created_by"] == "stages.expand" and dst.object_names == src.object_names
    assert set(dst.prescribed) == set(src.prescribed)
    assert len(dst.episode_ids) == r["accepted"]
    scene = build_scene(load_section(params, "scene", SceneConfig), ["bag"])
    faces = src.objects["bag"].faces
    for eid in dst.episode_ids:
        a = dst.episode_attrs(eid)
        assert (a["source"], a["task"], a["split"], a["accepted"], a["first_failure"]) == \
            ("worldcontact", TASK, "train", True, None)
        assert a["parent"] in ("ep_000000", "ep_000002") and a["objects"] == ["bag"] and a["model_sha256"] == weights
        e = dst.read_episode(eid)
        parent = src.read_window(a["parent"], 0, 1, ("x",))["x"][0]
        assert _edge_lengths(e["x"][0], faces) == pytest.approx(_edge_lengths(parent, faces), abs=1e-6)  # rigid
        assert np.array_equal(e["x"][0, :, 2], parent[:, 2]) and not e["v"][0].any()
        assert not np.allclose(e["x"][-1], e["x"][0])  # the model moved it
        assert np.allclose(e["link_poses"], scene.link_poses(e["action"]), atol=1e-6)
        assert e["action"][:, 13].max() > e["action"][:, 13].min()  # the right gripper opens and closes
        assert e["env_poses"].shape == (len(e["x"]), 1, 7)
        depth = table_and_robot_distance(scene, e["x"][1:, cloth_rows(scene)], e["link_poses"][1:])
        # contact-projected after every step; the self-crossing guard (params default expand.untangle) acts after the
        # projection and may keep a vertex nearer its previous state, inside a link that moved: within the source
        # checks' penetration tolerance (the projection's own invariant: tests/test_constraint_projection.py)
        tolerance = 1e-5 if params["expand"]["untangle"] == "none" else load_params()["validate"]["penetration_tol_m"]
        assert depth.min() > -tolerance


@pytest.mark.slow
def test_same_seed_same_output(run, tmp_path, params, store_path, model_dir):
    out, first = run
    again = expand(params, model_dir, store_path, tmp_path / "again.zarr", tmp_path / "again.json")
    a, b = TrajectoryStore(out / "expanded.zarr"), TrajectoryStore(tmp_path / "again.zarr")
    assert a.episode_ids == b.episode_ids
    for eid in a.episode_ids:
        assert a.episode_attrs(eid) == b.episode_attrs(eid)
        for k, arr in a.read_episode(eid).items():
            assert np.array_equal(arr, b.read_episode(eid)[k]), k
    timing = ("wall_s", "rollout_s", "trajectories_per_min", "accepted_per_min", "model_frames_per_s", "out",
              "environment", "timing")
    assert {k: v for k, v in first.items() if k not in timing} == {k: v for k, v in again.items() if k not in timing}


@pytest.mark.slow
def test_rejected_episodes_are_counted_per_check_and_not_written(tmp_path, params, store_path, model_dir):
    p = copy.deepcopy(params)
    p["validate"]["max_speed_m_s"] = 1e-4  # every moving rollout blows up
    p["expand"].update(max_attempts=3)
    r = expand(p, model_dir, store_path, tmp_path / "e.zarr", tmp_path / "e.json", tmp_path / "rejected.zarr")
    assert r["accepted"] == 0 and r["generated"] == 3 - r["infeasible_plans"] > 0
    assert r["rejections"]["blow_up"] == r["generated"] and not r["target_reached"]
    assert {e["reason"] for e in r["rejected_episodes"]} == {"blow_up"}
    assert TrajectoryStore(tmp_path / "e.zarr").episode_ids == []
    kept = TrajectoryStore(tmp_path / "rejected.zarr")  # the rejected plans, for the teacher check's recall
    assert len(kept.episode_ids) == r["generated"] and r["rejected_out"] == str(tmp_path / "rejected.zarr")
    for eid, logged in zip(kept.episode_ids, r["rejected_episodes"]):
        attrs = kept.episode_attrs(eid)
        assert not attrs["accepted"] and attrs["first_failure"] == "blow_up" and attrs["seed"] == logged["seed"]
        assert attrs["source"] == "worldcontact" and len(kept.read_episode(eid, ("x",))["x"]) == logged["frames"]
    p["validate"]["max_speed_m_s"] = 1e3
    p["expand"].update(task_check=True, max_attempts=2)  # the tiny model lifts nothing
    r = expand(p, model_dir, store_path, tmp_path / "t.zarr", tmp_path / "t.json")
    assert r["rejections"]["not_lifted"] == r["generated"] == 2 and r["accepted"] == 0


def test_a_passed_deadline_starts_no_batch_and_writes_whole_stores(run, tmp_path, params, store_path, model_dir):
    p = copy.deepcopy(params)
    p["expand"]["max_minutes"] = 1e-9
    r = expand(p, model_dir, store_path, tmp_path / "e.zarr", tmp_path / "e.json", tmp_path / "rejected.zarr")
    assert r["generated"] == r["attempts"] == 0 and r["stopped_early"]
    assert TrajectoryStore(tmp_path / "e.zarr").episode_ids == [] and json.loads((tmp_path / "e.json").read_text())
    assert not run[1]["stopped_early"]


def test_clear_errors(tmp_path, params, store_path, model_dir):
    with pytest.raises(FileNotFoundError, match="validate stage"):
        expand(params, model_dir, tmp_path / "none.zarr", tmp_path / "o.zarr", tmp_path / "r.json")
    with pytest.raises(FileNotFoundError, match="model.safetensors"):
        expand(params, tmp_path / "no_model", store_path, tmp_path / "o.zarr", tmp_path / "r.json")
    other = write_synthetic_store(tmp_path / "other.zarr", params, [("carry", "train")], frames=3)
    with pytest.raises(NoSourceEpisodesError, match="lift_handle.*carry"):
        expand(params, model_dir, other, tmp_path / "o.zarr", tmp_path / "r.json")
    with pytest.raises(ValueError, match="overwrite"):
        expand(params, model_dir, store_path, store_path, tmp_path / "r.json")
    with pytest.raises(ValueError, match="overwrite"):
        expand(params, model_dir, store_path, tmp_path / "o.zarr", tmp_path / "r.json", tmp_path / "o.zarr")
    assert not (tmp_path / "o.zarr").exists() and not (tmp_path / "r.json").exists()
    p = copy.deepcopy(params)
    p["expand"]["max_minutes"] = -1
    with pytest.raises(ParamsError, match="max_minutes"):
        load_section(p, "expand", ExpandConfig)
    p["expand"]["batch_size"] = 0
    with pytest.raises(ParamsError, match="expand: batch_size"):
        load_section(p, "expand", ExpandConfig)
    p["expand"] = {**params["expand"], "yaw_deg": 3}
    with pytest.raises(ParamsError, match="expand.yaw_deg"):
        load_section(p, "expand", ExpandConfig)


@pytest.mark.slow
def test_command_line(tmp_path, params, store_path, model_dir, capsys):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({k: v for k, v in params.items() if k != "_source"}))
    main(["--params", str(path), "--set", "expand.max_attempts=1", "--set", "expand.target_trajectories=3",
          "--model", str(model_dir), "--store", str(store_path), "--out", str(tmp_path / "c.zarr"),
          "--report", str(tmp_path / "c.json"), "--rejected-out", str(tmp_path / "rejected.zarr")])
    assert "expand lift_handle: 1/1 generated episodes accepted" in capsys.readouterr().out
    report = json.loads((tmp_path / "c.json").read_text())
    assert report["accepted"] == 1 and report["rejected_out"] == str(tmp_path / "rejected.zarr")
    assert TrajectoryStore(tmp_path / "rejected.zarr").episode_ids == []  # written, empty: nothing was rejected


@pytest.fixture(scope="module")
def rim(params):
    """lift_body (a rim grasp), its scene, a parent spec and the parent's state before settling."""
    scene = build_scene(load_section(params, "scene", SceneConfig), ["bag"])
    task = get_task("lift_body", params)
    spec = EpisodeSpec("lift_body", 7, 1, 0.08, 0.09)
    return task, scene, spec, task.initial_state(scene, spec, np.random.default_rng(spec.seed))


def _settled(x: np.ndarray, top_z: float) -> np.ndarray:
    """A stand-in for the simulator's settling: the dropped bag sags to 85 % of its height on the table."""
    y = x.astype(np.float64).copy()
    y[:, 2] = top_z + 0.85 * (y[:, 2] - y[:, 2].min())
    return y.astype(np.float32)


@pytest.mark.slow
def test_frame0_posture_is_planned_on_the_state_before_settling(rim, params):
    """The simulator agent plans frame 0's posture (settle_action) on the state before settling and lets the bag
    settle under it; expansion must do the same, not re-plan it on the settled (sagged) state."""
    task, scene, spec, initial = rim
    action0 = task.settle_action(scene, spec, initial)  # what the agent recorded as the parent's frame 0
    x0 = _settled(initial.x, scene.table.top_z)
    assert np.abs(task.settle_action(scene, spec, ObjectState(x0, np.zeros_like(x0))) - action0).max() > 1e-3
    attrs = {"task": spec.task, "seed": spec.seed, "cell": spec.cell, "speed": spec.speed, "amplitude": spec.amplitude}
    redrawn = presettle_state(task, scene, attrs, x0, action0)
    assert redrawn is not None and np.array_equal(redrawn, initial.x)
    assert presettle_state(task, scene, attrs, x0, scene.home_action()) is None  # not the agent's frame 0
    source = SourceEpisode("ep_p", spec.cell, x0, {}, redrawn, True)
    loose = load_section(params, "validate", ValidateConfig)
    still = load_section({**params, "expand": {**params["expand"], "yaw_range_deg": [0.0, 0.0],
                                               "shift_x_range_m": [0.0, 0.0], "shift_y_range_m": [0.0, 0.0]}},
                         "expand", ExpandConfig)
    planned = plan_episode(task, scene, source, EpisodeSpec("lift_body", 11, spec.cell, 0.07, 0.08), still, 0.04, loose)
    assert np.abs(planned.actions[0] - action0).max() < 1e-5 and np.array_equal(planned.x0, x0)
    cfg = load_section(params, "expand", ExpandConfig)
    moved = plan_episode(task, scene, source, EpisodeSpec("lift_body", 12, spec.cell, 0.07, 0.08), cfg, 0.04, loose)
    again = planar_transform(initial.x, moved.yaw_deg, moved.shift_m, x0[:, :2].astype(np.float64).mean(0))
    assert np.abs(moved.actions[0] - task.settle_action(scene, spec, ObjectState(again, np.zeros_like(again)))).max() < 1e-5


def test_a_plan_that_penetrates_at_frame_0_is_infeasible(rim, params):
    task, scene, spec, initial = rim
    cfg = load_section(load_params(), "validate", ValidateConfig)  # the module's params are LOOSE
    start = scene.home_action()
    x = _settled(initial.x, scene.table.top_z)
    check_clear_at_start(scene, x, start, cfg)  # clear: no error
    with pytest.raises(InfeasibleEpisode, match="frame-0 state penetrates"):
        check_clear_at_start(scene, x - np.float32([0.0, 0.0, 0.02]), start, cfg)  # 2 cm into the table
    centre = robot_boxes(scene, scene.link_poses(start[None]), ("right_link6",))[0][0, 0]
    wrist = x + (centre - x[0]).astype(np.float32)  # a vertex at the wrist box's centre
    with pytest.raises(InfeasibleEpisode, match=r"robot: \d+\.\d mm; tolerance 8\.0 mm"):
        check_clear_at_start(scene, wrist, start, cfg)


def test_parents_of_the_proposed_cell_come_first():
    x = np.zeros((3, 3), np.float32)
    sources = [SourceEpisode(f"ep_{i}", cell, x, {}, x) for i, cell in enumerate((0, 1, 1))]
    assert [pick_parent(sources, 1, i).eid for i in range(4)] == ["ep_1", "ep_2", "ep_1", "ep_2"]
    assert [pick_parent(sources, 2, i).eid for i in range(4)] == ["ep_0", "ep_1", "ep_2", "ep_0"]  # none: all in turn


def test_max_sources_takes_the_first_accepted_episodes_in_store_order(params, store_path):
    from wc.expand import source_episodes
    from wc.scene.episode_scenes import EpisodeScenes

    store = TrajectoryStore(store_path)
    task = get_task(TASK, params)
    scenes = EpisodeScenes(load_section(params, "scene", SceneConfig), store)
    every, _ = source_episodes(store, task, scenes)
    first, _ = source_episodes(store, task, scenes, limit=1)
    assert len(every) == 2 and [s.eid for s in first] == [every[0].eid]
    assert [s.eid for s in source_episodes(store, task, scenes, limit=5)[0]] == [s.eid for s in every]
    p = copy.deepcopy(params)
    p["expand"]["max_sources"] = -1
    with pytest.raises(ParamsError, match="max_sources must be >= 0"):
        load_section(p, "expand", ExpandConfig)
