"""Stage `validate` on a small raw store built from the real scene meshes: accepted episodes, splits,
report counts, determinism, atomic output and clear errors."""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import wc.data.store as store_module
from stages.validate import main
from tests.conftest import load_params
from tests.stage_run import assert_one_line_error, run_stage
from wc.config import ParamsError, load_section, params_hash
from wc.data.store import TrajectoryStore, TrajectoryWriter
from wc.scene.config import SceneConfig
from wc.scene.piper import ARM_BODY_NAMES
from wc.scene.scene import build_scene
from wc.validate import PREDICATES
from wc.validate.split import split_counts, split_episodes
from wc.scene.episode_scenes import EpisodeScenes
from wc.validate.stage import NoAcceptedEpisodesError, episode_state, validate

T = 10
HELD = {"cube": {"link": "right_link6", "local_pose": [0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]}}
# Explicit tolerances, so that calibrating params.yaml does not change what these tests plant.
VALIDATE = dict(max_speed_m_s=3.0, max_edge_strain=1.0, penetration_tol_m=0.004, self_intersection_every=5,
                release_opening_m=0.03, adhesion_radius_m=0.01, adhesion_window_s=0.4, adhesion_rise_m=0.03,
                workspace_min_m=[-0.55, -0.45, -0.01], workspace_max_m=[0.55, 0.45, 0.7],
                min_visible_fraction=0.5, view_camera="top", val_per_task=1, test_per_task=1, split_seed=0)
# episode id -> (task, kind); kinds are built in _episode
EPISODES = {
    "ep_000000": ("lift_handle", "clean"),
    "ep_000001": ("lift_handle", "clean"),
    "ep_000002": ("lift_handle", "clean"),
    "ep_000003": ("lift_handle", "into_table"),
    "ep_000004": ("lift_handle", "not_lifted"),
    "ep_000005": ("place_sphere", "sphere"),
    "ep_000006": ("place_sphere", "sphere"),
    "ep_000007": ("place_sphere", "into_sphere"),
    "ep_000008": ("carry_cube", "held_cube"),
}
CLEAN = ["ep_000000", "ep_000001", "ep_000002", "ep_000005", "ep_000006", "ep_000008"]


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    p = load_params()
    p["validate"] = copy.deepcopy(VALIDATE)
    return p


def _episode(scene_cfg: SceneConfig, kind: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Arrays and layout attrs of one planted episode: the bag at rest on the table, robot at home."""
    held = {"cube": ("right_link6", HELD["cube"]["local_pose"])} if kind == "held_cube" else {}
    objects = ["bag", "sphere"] if kind in ("sphere", "into_sphere") else ["bag"]
    scene = build_scene(scene_cfg, objects, held=held)
    bag = scene.objects["bag"].vertices.astype(np.float64)
    x = np.repeat(bag[None], T, axis=0)
    if kind in ("into_table", "dropped_into_table"):
        x[5:, :, 2] -= 0.02  # the whole bag 2 cm down: its bottom inside the table from frame 5
    if "sphere" in objects:
        sphere = scene.objects["sphere"].vertices.astype(np.float64)
        beside = np.array([bag[:, 0].max() + 0.03 + scene_cfg.sphere.radius_m, 0.0, scene_cfg.sphere.radius_m + 5e-4])
        rows = np.repeat((sphere + beside)[None], T, axis=0)
        if kind == "into_sphere":  # rolled onto the bag's side: a bag vertex 1 cm inside from frame 6
            side = bag[np.argmin(-bag[:, 0] + np.abs(bag[:, 2] - 0.05))]
            rows[6:] = sphere + side + (scene_cfg.sphere.radius_m - 0.01) * np.array([1.0, 0.0, 0.0])
        x = np.concatenate([x, rows], axis=1)
    action = np.repeat(scene.home_action()[None], T, axis=0)
    arrays = dict(x=x, v=np.zeros_like(x), action=action, link_poses=scene.link_poses(action),
                  env_poses=np.repeat(scene.env_poses()[None], T, axis=0))
    attrs = {"objects": objects, "links": list(scene.link_names)}
    if held:
        attrs["held"] = HELD
    return arrays, attrs


def _write_raw(path: Path, scene_cfg: SceneConfig, episodes: dict[str, tuple[str, str]]) -> Path:
    full = build_scene(scene_cfg, ["bag", "sphere", "cube"], held={"cube": ("right_link6", HELD["cube"]["local_pose"])})
    with TrajectoryWriter(path, dt=0.04, substeps=20, params_hash="raw-hash", created_by="test",
                          object_order=list(full.objects), link_names=list(full.link_names),
                          env_names=list(full.env_names), chunk_frames=4) as w:
        w.add_scene(full)
        for i, (eid, (task, kind)) in enumerate(episodes.items()):
            arrays, layout = _episode(scene_cfg, kind)
            reason = {"not_lifted": "not_lifted", "dropped_into_table": "dropped"}.get(kind)  # simulate's verdict
            w.add_episode(**arrays, episode_id=eid, task=task, seed=100 + i, cell=i % 3, speed=0.08,
                          amplitude=0.16, split=None, accepted=reason is None,
                          first_failure=reason, source="simulator", **layout)
    return path


@pytest.fixture(scope="module")
def raw(tmp_path_factory, params) -> Path:
    scene_cfg = load_section(params, "scene", SceneConfig)
    return _write_raw(tmp_path_factory.mktemp("raw") / "raw.zarr", scene_cfg, EPISODES)


@pytest.fixture(scope="module")
def result(tmp_path_factory, raw, params) -> tuple[dict[str, Any], Path, Path]:
    d = tmp_path_factory.mktemp("out")
    report = validate(params, raw, d / "trajectories.zarr", d / "validate.json")
    return report, d / "trajectories.zarr", d / "validate.json"


@pytest.mark.slow
def test_output_holds_exactly_the_clean_episodes(result, raw):
    report, out, _ = result
    dst, src = TrajectoryStore(out), TrajectoryStore(raw)
    assert dst.episode_ids == CLEAN
    assert dst.attrs["created_by"] == "stages.validate"
    for eid in CLEAN:
        a = dst.episode_attrs(eid)
        assert a["accepted"] is True and a["first_failure"] is None and a["split"] in ("train", "val", "test")
        assert a["objects"] == src.episode_objects(eid) and a["links"] == src.episode_links(eid)
        assert np.array_equal(dst.read_episode(eid)["x"], src.read_episode(eid)["x"])
    assert dst.episode_attrs("ep_000008")["held"] == HELD


@pytest.mark.slow
def test_splits_follow_the_rule(result, params):
    report, out, _ = result
    dst = TrajectoryStore(out)
    splits = {eid: dst.episode_attrs(eid)["split"] for eid in dst.episode_ids}
    tasks = {eid: dst.episode_attrs(eid)["task"] for eid in dst.episode_ids}
    assert splits == split_episodes(tasks, 1, 1, 0)
    per_task = {t: sorted(splits[e] for e in splits if tasks[e] == t) for t in set(tasks.values())}
    assert per_task == {"lift_handle": ["test", "train", "val"],  # 3 accepted: one each
                        "place_sphere": ["test", "train"],  # 2: test before val, one stays in train
                        "carry_cube": ["train"]}  # 1: always train


@pytest.mark.slow
def test_report_counts(result, params):
    report, _, path = result
    assert json.loads(path.read_text()) == json.loads(json.dumps(report))
    assert report["episodes"] == 9 and report["accepted"] == 6 and report["rejected"] == 3
    assert report["rejections"] == {**{p: 0 for p in PREDICATES}, "penetration": 2, "not_lifted": 1}
    assert report["splits"] == {"train": 3, "val": 1, "test": 2}
    lift = report["tasks"]["lift_handle"]
    assert {k: lift[k] for k in ("episodes", "accepted", "train", "val", "test")} == \
        {"episodes": 5, "accepted": 3, "train": 1, "val": 1, "test": 1}
    assert lift["rejections"]["penetration"] == 1 and lift["rejections"]["not_lifted"] == 1
    assert report["tasks"]["place_sphere"]["rejections"]["penetration"] == 1
    assert report["tasks"]["carry_cube"]["accepted"] == 1
    assert report["rejected_episodes"] == {
        "ep_000003": {"task": "lift_handle", "reason": "penetration", "frame": 5, "by": "validate"},
        "ep_000004": {"task": "lift_handle", "reason": "not_lifted", "frame": None, "by": "simulate"},
        "ep_000007": {"task": "place_sphere", "reason": "penetration", "frame": 6, "by": "validate"},
    }
    assert report["params_hash"] == params_hash(params, ["validate", "scene"])
    assert report["source_params_hash"] == "raw-hash"
    assert report["wall_s"] > 0 and report["environment"]["device"] == "cpu"


@pytest.mark.slow
def test_split_is_deterministic(result, raw, params, tmp_path):
    first, out, _ = result
    again = validate(params, raw, tmp_path / "again.zarr", tmp_path / "again.json")
    a, b = TrajectoryStore(out), TrajectoryStore(tmp_path / "again.zarr")
    assert [a.episode_attrs(e)["split"] for e in CLEAN] == [b.episode_attrs(e)["split"] for e in CLEAN]
    assert again["tasks"] == first["tasks"]


@pytest.mark.slow
def test_task_failures_kept_for_training_only(params, tmp_path):
    """train_on_task_failures: a physically clean episode whose task failed joins the train split with accepted
    false; one whose task failed but whose state is bad stays out; the accepted episodes and splits are unchanged;
    expand's sources and render skip the kept failure, training's train phases include it."""
    from wc.render.stage import select_episodes
    from wc.train.data import phases_of
    scene_cfg = load_section(params, "scene", SceneConfig)
    episodes = {**EPISODES, "ep_000009": ("lift_handle", "dropped_into_table")}
    raw = _write_raw(tmp_path / "raw.zarr", scene_cfg, episodes)
    plain = validate(params, raw, tmp_path / "plain.zarr", tmp_path / "plain.json")
    keep = copy.deepcopy(params)
    keep["validate"]["train_on_task_failures"] = True
    report = validate(keep, raw, tmp_path / "keep.zarr", tmp_path / "keep.json")
    assert report["task_failures_kept"] == 1 and plain["task_failures_kept"] == 0
    assert report["tasks"]["lift_handle"]["task_failures_kept"] == 1
    assert report["accepted"] == plain["accepted"] == 6 and report["rejected_episodes"] == plain["rejected_episodes"]
    store = TrajectoryStore(tmp_path / "keep.zarr")
    assert store.episode_ids == sorted(CLEAN + ["ep_000004"])
    kept = store.episode_attrs("ep_000004")
    assert (kept["split"], kept["accepted"], kept["first_failure"]) == ("train", False, "not_lifted")
    plain_store = TrajectoryStore(tmp_path / "plain.zarr")
    assert all(store.episode_attrs(e)["split"] == plain_store.episode_attrs(e)["split"] for e in CLEAN)
    assert "ep_000004" not in store.episodes_where(task="lift_handle", accepted=True)
    assert select_episodes(store, None) == CLEAN
    assert "ep_000004" in {p.episode for p in phases_of(store, "train")}


def test_split_rule():
    assert split_counts(0, 2, 2) == {"train": 0, "val": 0, "test": 0}
    assert split_counts(1, 2, 2) == {"train": 1, "val": 0, "test": 0}
    assert split_counts(2, 2, 2) == {"train": 1, "val": 0, "test": 1}
    assert split_counts(4, 2, 2) == {"train": 1, "val": 1, "test": 2}
    assert split_counts(9, 2, 2) == {"train": 5, "val": 2, "test": 2}
    assert split_counts(3, 0, 1) == {"train": 2, "val": 0, "test": 1}
    tasks = {f"ep_{i:06d}": ("a" if i % 3 else "b") for i in range(30)}
    split = split_episodes(tasks, 2, 3, seed=7)
    assert split == split_episodes(dict(reversed(tasks.items())), 2, 3, seed=7)  # input order is irrelevant
    assert set(split) == set(tasks)
    for t in "ab":
        labels = [split[e] for e in tasks if tasks[e] == t]
        assert (labels.count("test"), labels.count("val")) == (3, 2)
    others = {e: s for e, s in split_episodes({e: t for e, t in tasks.items() if t == "a"}, 2, 3, 7).items()}
    assert others == {e: split[e] for e in tasks if tasks[e] == "a"}  # a task's split ignores the other tasks
    seeds = [split_episodes(tasks, 2, 3, seed=s) for s in range(5)]
    assert len({tuple(sorted(s.items())) for s in seeds}) > 1


@pytest.mark.slow
def test_cli(raw, params, tmp_path, capsys):
    params_file = tmp_path / "params.yaml"
    params_file.write_text(json.dumps({k: v for k, v in params.items() if k != "_source"}))  # JSON is YAML
    main(["--params", str(params_file), "--set", "validate.test_per_task=0", "--raw", str(raw),
          "--out", str(tmp_path / "t.zarr"), "--report", str(tmp_path / "r.json")])
    assert "6/9 episodes accepted (train 4, val 2, test 0)" in capsys.readouterr().out


def _leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if ".tmp-" in p.name)


@pytest.mark.slow
def test_atomic_output_on_failure(raw, params, tmp_path, monkeypatch):
    out = tmp_path / "trajectories.zarr"
    validate(params, raw, out, tmp_path / "validate.json")
    before = TrajectoryStore(out).episode_ids
    calls = []
    add_episode = store_module.TrajectoryWriter.add_episode

    def fail_third(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise OSError("disk full")
        return add_episode(self, *args, **kwargs)

    monkeypatch.setattr(store_module.TrajectoryWriter, "add_episode", fail_third)
    with pytest.raises(OSError, match="disk full"):
        validate(params, raw, out, tmp_path / "validate.json")
    assert TrajectoryStore(out).episode_ids == before  # the previous store is untouched
    calls.clear()
    with pytest.raises(OSError, match="disk full"):
        validate(params, raw, tmp_path / "fresh.zarr", tmp_path / "fresh.json")
    assert not (tmp_path / "fresh.zarr").exists() and not (tmp_path / "fresh.json").exists()
    assert _leftovers(tmp_path) == []


def test_missing_raw_store(params, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nowhere\.zarr.*simulate"):
        validate(params, tmp_path / "nowhere.zarr", tmp_path / "t.zarr", tmp_path / "r.json")
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("key,value,match", [
    ("penetration_tol_m", "deep", "validate.penetration_tol_m"),
    ("split_seed", None, "validate.split_seed"),
    ("test_per_task", -1, "test_per_task"),
    ("colour", 1, "validate.colour"),
    ("view_camera", "side", "validate.view_camera"),
])
def test_malformed_params(raw, params, tmp_path, key, value, match):
    bad = copy.deepcopy(params)
    if value is None:
        del bad["validate"][key]
    else:
        bad["validate"][key] = value
    with pytest.raises(ParamsError, match=match):
        validate(bad, raw, tmp_path / "t.zarr", tmp_path / "r.json")
    assert not (tmp_path / "t.zarr").exists()


def test_corrupt_raw_store(raw, params, tmp_path):
    broken = tmp_path / "raw.zarr"
    shutil.copytree(raw, broken)
    shutil.rmtree(broken / "episodes" / "ep_000001" / "x" / "c" / "1")  # frames 4..7 of x lost
    with pytest.raises(ValueError, match="corrupt episode ep_000001"):
        validate(params, broken, tmp_path / "t.zarr", tmp_path / "r.json")
    (broken / "zarr.json").unlink()
    with pytest.raises(ValueError, match="not a worldcontact trajectory store"):
        validate(params, broken, tmp_path / "t.zarr", tmp_path / "r.json")
    assert not (tmp_path / "t.zarr").exists()


@pytest.mark.slow
def test_stage_names_a_chunk_overwritten_with_garbage(raw, tmp_path):
    """`python -m stages.validate` on a store whose chunk of frames 4-7 of ep_000001's x holds random bytes: status
    2 and one line naming the store, the episode, the array and the chunk (zstd's own error names none)."""
    broken = tmp_path / "raw.zarr"
    shutil.copytree(raw, broken)
    chunk = broken / "episodes" / "ep_000001" / "x" / "c" / "1" / "0" / "0"
    chunk.write_bytes(np.random.default_rng(0).bytes(chunk.stat().st_size))
    out = tmp_path / "t.zarr"
    done = run_stage("validate", "--raw", str(broken), "--out", str(out), "--report", str(tmp_path / "r.json"))
    assert_one_line_error(done, "validate", str(broken), "corrupt episode ep_000001", "array 'x'", "chunk c/1/0/0",
                          "frames 4-7", "does not decode", progress=True)
    assert not out.exists()


def test_scene_params_changed_since_simulate(raw, params, tmp_path):
    changed = copy.deepcopy(params)
    changed["scene"]["bag"]["target_vertices"] = 120
    with pytest.raises(ValueError, match="scene params changed"):
        validate(changed, raw, tmp_path / "t.zarr", tmp_path / "r.json")


def test_no_accepted_episode(params, tmp_path):
    scene_cfg = load_section(params, "scene", SceneConfig)
    raw = _write_raw(tmp_path / "raw.zarr", scene_cfg, {"ep_000000": ("lift_handle", "not_lifted"),
                                                       "ep_000001": ("lift_handle", "into_table")})
    with pytest.raises(NoAcceptedEpisodesError, match="none of the 2 episodes"):
        validate(params, raw, tmp_path / "t.zarr", tmp_path / "r.json")
    assert not (tmp_path / "t.zarr").exists()
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["accepted"] == 0 and report["out"] is None
    assert report["rejections"]["not_lifted"] == 1 and report["rejections"]["penetration"] == 1


def test_episode_without_the_held_link_column(raw, params):
    """Link columns are matched by name; a body the scene needs but the episode lacks is a clear error."""
    src = TrajectoryStore(raw)
    scenes = EpisodeScenes(load_section(params, "scene", SceneConfig), src)
    held_scene = scenes.scene("ep_000008")
    assert held_scene.link_names == (*ARM_BODY_NAMES, "held_cube")
    assert episode_state(src, "ep_000008", held_scene)["link_poses"].shape == (T, len(ARM_BODY_NAMES) + 1, 7)
    with pytest.raises(ValueError, match=r"ep_000000 has no link_poses columns for \['held_cube'\]"):
        episode_state(src, "ep_000000", held_scene)
