"""Stage `expand` rejecting generated episodes by penetration, self-intersection and the workspace box: each is
counted under its check in the report and written to the rejected store with that first failure, which the source
data's checks, run again on the stored episode, confirm at the same frame. (blow_up and the task's not_lifted:
tests/test_expand.py.)

Every generated episode starts from a parent's frame 0 moved rigidly, so a parent planted with a fold that crosses
the bag's far wall starts a crossing rollout; the tiny untrained model, without the per-step projection, pushes the
bag into the table within a few frames."""

from __future__ import annotations

import copy
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr

from tests.conftest import load_params
from tests.expand_inputs import expand_params, write_source_store, write_tiny_model
from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.expand import expand
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.validate.config import ValidateConfig
from wc.validate.predicates import PREDICATES, cloth_rows, first_failure, table_distance
from wc.validate.self_intersection import crossing_edges, unique_edges

PLAIN, FOLDED = "ep_000000", "ep_000002"  # the source store's two lift_handle parents, in store order
UNPROJECTED = dict(engine="batches", projection="none", untangle="none", self_contact=False, max_attempts=2,
                   batch_size=2, target_trajectories=4)  # the reference engine: the slot engine always projects


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    return expand_params()


@pytest.fixture(scope="module")
def scene(params):
    return build_scene(load_section(params, "scene", SceneConfig), ["bag"])


@pytest.fixture(scope="module")
def store_path(tmp_path_factory, params, scene) -> Path:
    """The expand tests' source store with FOLDED's frame 0 planted with a fold: the bag's outermost mid-height
    vertex on +x pushed through the bag to 1 cm beyond its far wall, so that its edges cross that wall."""
    path = write_source_store(tmp_path_factory.mktemp("store"), params)
    x = zarr.open_group(str(path), mode="r+")[f"episodes/{FOLDED}/x"]
    x0 = x[0]
    centre = x0.mean(axis=0)
    mid = np.flatnonzero(np.abs(x0[:, 2] - centre[2]) < 0.01)
    i = mid[np.argmax(x0[mid, 0])]
    far_wall = x0[mid, 0].min()
    x0[i, 0] = far_wall - 0.01
    x[0] = x0
    bag = scene.objects["bag"]
    assert (crossing_edges(x0, bag.faces, unique_edges(bag.faces)) >= 0).any(), "the planted fold crosses nothing"
    return path


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory, params) -> Path:
    return write_tiny_model(tmp_path_factory.mktemp("models"), params)


def _rejected(r: dict[str, Any], rejected_out: Path, params: dict[str, Any], scene) -> list[tuple[str, str, int]]:
    """(parent, check, frame) per rejected episode as the report logged it, in planning order, after checking that
    the rejected store holds the same episodes with that first failure, that the source checks run again on each
    stored episode agree, and that the report counts each check's rejections."""
    store = TrajectoryStore(rejected_out)
    assert len(store.episode_ids) == len(r["rejected_episodes"]) == r["generated"] - r["accepted"]
    cfg = load_section(params, "validate", ValidateConfig)
    logged = []
    for eid, entry in zip(store.episode_ids, r["rejected_episodes"]):
        attrs, e = store.episode_attrs(eid), store.read_episode(eid)
        assert (attrs["parent"], attrs["seed"], attrs["accepted"]) == (entry["parent"], entry["seed"], False)
        assert attrs["first_failure"] == entry["reason"]
        again = first_failure(scene, e["x"], e["v"], e["action"], e["link_poses"], cfg, frame_dt_s=store.dt)
        assert again == (entry["reason"], entry["frame"]), (eid, again, entry)
        logged.append((entry["parent"], entry["reason"], entry["frame"]))
    assert set(r["rejections"]) >= set(PREDICATES)
    assert {name: n for name, n in r["rejections"].items() if n} == Counter(reason for _, reason, _ in logged)
    return logged


@pytest.mark.slow
def test_a_crossing_fold_and_a_bag_outside_the_workspace_are_rejected(tmp_path, params, scene, store_path, model_dir):
    """The folded parent's episode crosses itself at frame 0; the plain parent's stands taller than a workspace box
    lowered to 5 mm under its top. (The folded bag is outside the box too: self-intersection is checked first.)"""
    p = copy.deepcopy(params)
    p["expand"].update(UNPROJECTED)
    top = TrajectoryStore(store_path).read_window(PLAIN, 0, 1, ("x",))["x"][0, :, 2].max()
    p["validate"]["workspace_max_m"] = [10.0, 10.0, float(top) - 0.005]
    r = expand(p, model_dir, store_path, tmp_path / "e.zarr", tmp_path / "e.json", tmp_path / "rejected.zarr")
    assert r["generated"] == 2 and r["accepted"] == 0 and r["infeasible_plans"] == 0
    assert _rejected(r, tmp_path / "rejected.zarr", p, scene) == [(PLAIN, "workspace", 0),
                                                                  (FOLDED, "self_intersection", 0)]


@pytest.mark.slow
def test_a_rollout_pushed_into_the_table_is_rejected(tmp_path, params, scene, store_path, model_dir):
    """Without the per-step projection the tiny model's rollout sinks into the table beyond the shipped tolerance;
    the report names the table and the depth, which the test measures again."""
    p = copy.deepcopy(params)
    p["expand"].update(UNPROJECTED, max_sources=1)  # the plain parent only
    p["validate"]["penetration_tol_m"] = tol = load_params()["validate"]["penetration_tol_m"]
    r = expand(p, model_dir, store_path, tmp_path / "e.zarr", tmp_path / "e.json", tmp_path / "rejected.zarr")
    assert r["generated"] == 2 and r["accepted"] == 0
    logged = _rejected(r, tmp_path / "rejected.zarr", p, scene)
    assert [(parent, reason) for parent, reason, _ in logged] == [(PLAIN, "penetration")] * 2
    rejected = TrajectoryStore(tmp_path / "rejected.zarr")
    for eid, entry in zip(rejected.episode_ids, r["rejected_episodes"]):
        x = rejected.read_episode(eid, ("x",))["x"][entry["frame"], cloth_rows(scene)]
        depth = -table_distance(scene, x).min()
        assert entry["body"] == "table" and entry["depth_m"] == pytest.approx(depth, abs=1e-6) and depth > tol
