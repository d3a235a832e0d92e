"""Stage `dataset` on tiny synthetic stores: both LeRobot datasets load in stock LeRobot with the right
shapes, counts, fps and task; state / action / video frames are aligned; clear errors; `push` fails
cleanly offline. Run with HF_HUB_OFFLINE=1: nothing here touches the Hub."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stages.dataset import main
from stages.push import main as push_main
from wc.policy.hub import PushError
from wc.config import ParamsError
from wc.data.store import TrajectoryStore
from wc.policy.comparison import FLAG
from wc.policy.dataset import PROVENANCE_FILE, fps_of, right_arm_state_action, select_episodes
from wc.policy.dataset_shards import shard_bounds
from wc.policy.dataset_stage import build_datasets
from wc.policy.video_frame_check import missing_video_frames
from wc.render.frames import RenderedStore, RenderedWriter
from tests.conftest import load_params
from tests.synthetic_store import write_synthetic_store

T = 12  # frames per episode
SIZE = 32  # px
STEP = 20  # intensity step per frame: frame k of `top` is flat grey 10 + STEP k, of `wrist` 245 - STEP k
TOLERANCE = 8  # of 255: lossy video codec on flat frames
REPO = "worldcontact"
# carry moves the right arm (the "carry" kind's base yaw sweeps); fall does not and is another task
SOURCE = [("carry", "train"), ("fall", "train"), ("carry", "test"), ("carry", "val")]
EXPANDED = [("carry", "train"), ("fall", "train"), ("carry", "train")]


def _grey(values: np.ndarray) -> np.ndarray:
    """(len(values), SIZE, SIZE, 3) uint8 frames, each one flat grey level."""
    return np.broadcast_to(values.astype(np.uint8)[:, None, None, None], (len(values), SIZE, SIZE, 3)).copy()


def expected_grey(camera: str, k: np.ndarray) -> np.ndarray:
    return 10 + STEP * k if camera == "top" else 245 - STEP * k


def write_frames(path: Path, store: TrajectoryStore, frames: dict[str, int] | None = None) -> Path:
    """A rendered store for every episode of `store`; `frames` overrides an episode's frame count."""
    with RenderedWriter(path, cameras=["top", "wrist"], width=SIZE, height=SIZE, fps=1 / store.dt) as w:
        for eid in store.episode_ids:
            k = np.arange((frames or {}).get(eid, store.num_frames(eid)))
            w.add_episode(eid, {cam: _grey(expected_grey(cam, k)) for cam in ("top", "wrist")})
    return path


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    p = load_params()
    p["dataset"] = {**p["dataset"], "task": "carry", "splits": ["train", "test"]}  # the val episode stays out
    return p


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory, params: dict[str, Any]) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("inputs")
    src = write_synthetic_store(root / "source.zarr", params, SOURCE, frames=T, seed=0)
    exp = write_synthetic_store(root / "expanded.zarr", params, EXPANDED, frames=T, seed=1)
    return {"source_trajectories": src, "source_frames": write_frames(root / "source_frames.zarr", TrajectoryStore(src)),
            "expanded_trajectories": exp,
            "expanded_frames": write_frames(root / "expanded_frames.zarr", TrajectoryStore(exp))}


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory, params: dict[str, Any], inputs: dict[str, Path]) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("out")
    report = build_datasets(params, **inputs, out=out / "lerobot", report=out / "dataset.json")
    return {"out": out / "lerobot", "report": report, "report_path": out / "dataset.json"}


def _load(root: Path, name: str) -> Any:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(f"{REPO}/{name}", root=root / name)


def check_video_frames(frames: dict[str, np.ndarray], mask: np.ndarray) -> None:
    """Decoded frame k of each camera is rendered frame k (its grey level), within codec tolerance."""
    for cam in ("top", "wrist"):
        grey = frames[f"observation.images.{cam}"][mask].mean(axis=(1, 2, 3)) * 255
        np.testing.assert_allclose(grey, expected_grey(cam, frames["frame_index"][mask]), atol=TOLERANCE)


def _all_frames(ds: Any) -> dict[str, np.ndarray]:
    """Every frame of `ds` through a stock torch DataLoader, as numpy arrays keyed by feature."""
    import torch

    out: dict[str, list] = {}
    for batch in torch.utils.data.DataLoader(ds, batch_size=16, shuffle=False, num_workers=0):
        for key, value in batch.items():
            out.setdefault(key, []).extend(value.numpy() if isinstance(value, torch.Tensor) else value)
    return {k: np.stack(v) if k != "task" else np.array(v) for k, v in out.items()}


def test_alignment_of_state_and_action() -> None:
    action = np.random.default_rng(0).normal(size=(5, 14)).astype(np.float32)
    state, act = right_arm_state_action(action)
    np.testing.assert_array_equal(state, action[:, 7:14])
    np.testing.assert_array_equal(act[:-1], state[1:])
    np.testing.assert_array_equal(act[-1], state[-1])
    with pytest.raises(ValueError, match="shape"):
        right_arm_state_action(action[:, :7])


def test_fps_from_dt() -> None:
    assert fps_of(0.04) == 25 and fps_of(0.1) == 10
    with pytest.raises(ValueError, match="not an integer"):
        fps_of(0.03)


@pytest.mark.slow
def test_report_counts(built: dict[str, Any], inputs: dict[str, Path]) -> None:
    report = json.loads(built["report_path"].read_text())
    src, exp = TrajectoryStore(inputs["source_trajectories"]), TrajectoryStore(inputs["expanded_trajectories"])
    n_src = len([e for e in src.episodes_where(task="carry") if src.episode_attrs(e)["split"] in ("train", "test")])
    n_exp = len(exp.episodes_where(task="carry"))
    assert report["datasets"]["source"]["episodes"] == n_src == 2
    assert report["datasets"]["expanded"]["episodes"] == n_src + n_exp == 4
    assert report["datasets"]["expanded"]["frames"] == (n_src + n_exp) * T
    assert report["generated_episodes"] == n_exp and report[FLAG] is False
    assert report["skipped_episodes"]["source"] == {"other_task": 1, "split": 1, "rejected": 0}
    assert report["skipped_episodes"]["expanded"]["other_task"] == 1
    assert len(report["params_hash"]) == 16 and report["wall_s"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["source", "expanded"])
def test_loads_in_stock_lerobot(built: dict[str, Any], inputs: dict[str, Path], name: str) -> None:
    ds = _load(built["out"], name)
    summary = built["report"]["datasets"][name]
    assert ds.num_episodes == summary["episodes"] and ds.num_frames == summary["frames"] == len(ds)
    assert ds.fps == 25 and ds.meta.robot_type == "piper"
    assert set(ds.meta.video_keys) == {"observation.images.top", "observation.images.wrist"}
    frames = _all_frames(ds)
    n = ds.num_frames
    assert frames["observation.images.top"].shape == (n, 3, SIZE, SIZE)
    assert frames["observation.images.wrist"].shape == (n, 3, SIZE, SIZE)
    assert frames["observation.state"].shape == (n, 7) and frames["action"].shape == (n, 7)
    assert set(frames["task"]) == {"right grasp and lift"}

    # state and action follow the trajectory store: state[k] = action_store[k, 7:], action[k] = state[k + 1]
    provenance = json.loads((built["out"] / name / PROVENANCE_FILE).read_text())
    assert [p["store"] for p in provenance] == ["source"] * 2 + ["expanded"] * (len(provenance) - 2)
    stores = {s: TrajectoryStore(inputs[f"{s}_trajectories"]) for s in ("source", "expanded")}
    moved = 0
    for row in provenance:
        mask = frames["episode_index"] == row["episode_index"]
        k = frames["frame_index"][mask]
        np.testing.assert_array_equal(k, np.arange(T))
        store_action = stores[row["store"]].read_episode(row["episode_id"], ("action",))["action"]
        state, action = frames["observation.state"][mask], frames["action"][mask]
        np.testing.assert_allclose(state, store_action[:, 7:14], atol=1e-6)
        np.testing.assert_allclose(action[:-1], state[1:], atol=1e-6)
        np.testing.assert_allclose(action[-1], state[-1], atol=1e-6)
        moved += int(np.abs(np.diff(state, axis=0)).max() > 1e-4)
        np.testing.assert_allclose(frames["timestamp"][mask], k / 25, atol=1e-4)
        check_video_frames(frames, mask)
    assert moved == len(provenance)  # the check above would be vacuous on a still arm


@pytest.mark.slow
def test_card_and_atomic_output(built: dict[str, Any]) -> None:
    for name in ("source", "expanded"):
        card = (built["out"] / name / "README.md").read_text()
        assert "right grasp and lift" in card and "action[k] == observation.state[k+1]" in card
        render_step = "3. The `render` stage" if name == "expanded" else "2. The `render` stage"
        assert render_step in card  # the steps are numbered in order whether or not expand added episodes
        assert built["report"]["params_hash"] in card
    assert sorted(p.name for p in built["out"].iterdir()) == ["expanded", "source"]  # no temporary left behind


def test_shard_bounds_cover_the_episodes_in_order() -> None:
    assert shard_bounds(10, 3) == [(0, 3), (3, 7), (7, 10)]
    assert shard_bounds(2, 8) == [(0, 1), (1, 2)]  # never an empty shard
    assert shard_bounds(5, 1) == [(0, 5)]
    with pytest.raises(ValueError, match="shards >= 1"):
        shard_bounds(5, 0)


@pytest.mark.slow
def test_datasets_written_in_shards_equal_the_serial_ones(built: dict[str, Any], tmp_path: Path,
                                                          params: dict[str, Any], inputs: dict[str, Path]) -> None:
    """dataset.workers 3: the expanded dataset's 4 episodes are written by 3 processes and joined by lerobot's
    aggregation; every frame (state, action, indices, decoded pixels) and the provenance equal the serial build's,
    and the params hash ignores the worker count."""
    sharded = copy.deepcopy(params)
    sharded["dataset"]["workers"] = 3
    report = build_datasets(sharded, **inputs, out=tmp_path / "lerobot", report=tmp_path / "r.json")
    assert report["params_hash"] == built["report"]["params_hash"]
    for name in ("source", "expanded"):
        serial, parallel = _load(built["out"], name), _load(tmp_path / "lerobot", name)
        assert (parallel.num_episodes, parallel.num_frames) == (serial.num_episodes, serial.num_frames)
        assert missing_video_frames(tmp_path / "lerobot" / name) == []
        a, b = _all_frames(serial), _all_frames(parallel)
        assert sorted(a) == sorted(b)
        for key in a:
            np.testing.assert_array_equal(b[key], a[key], err_msg=f"{name}: {key}")
        assert ((tmp_path / "lerobot" / name / PROVENANCE_FILE).read_text()
                == (built["out"] / name / PROVENANCE_FILE).read_text())
    assert sorted(p.name for p in (tmp_path / "lerobot").iterdir()) == ["expanded", "source"]  # no shard left


def test_missing_expanded_inputs_fail_before_writing(tmp_path: Path, params: dict[str, Any],
                                                     inputs: dict[str, Path]) -> None:
    args = {**inputs, "expanded_trajectories": tmp_path / "absent.zarr"}
    with pytest.raises(FileNotFoundError, match="include_expanded=false"):
        build_datasets(params, **args, out=tmp_path / "lerobot", report=tmp_path / "r.json")
    assert not (tmp_path / "lerobot").exists() and not (tmp_path / "r.json").exists()


@pytest.mark.slow
def test_an_expansion_without_generated_episodes_is_flagged_or_refused(tmp_path: Path, params: dict[str, Any],
                                                                      inputs: dict[str, Path]) -> None:
    """Only another task's episodes in the expanded store: the two datasets hold the same episodes. The report says
    so in its top-level flag; with dataset.require_generated the stage fails before writing anything."""
    other = write_synthetic_store(tmp_path / "other.zarr", params, [("fall", "train")], frames=T, seed=2)
    args = {**inputs, "expanded_trajectories": other,
            "expanded_frames": write_frames(tmp_path / "other_frames.zarr", TrajectoryStore(other))}
    strict = copy.deepcopy(params)
    strict["dataset"] = {**strict["dataset"], "require_generated": True, "splits": ["test"]}
    with pytest.raises(ValueError, match="no accepted generated 'carry' episode.*require_generated"):
        build_datasets(strict, **args, out=tmp_path / "lerobot", report=tmp_path / "r.json")
    assert not (tmp_path / "lerobot").exists() and not (tmp_path / "r.json").exists()
    lenient = copy.deepcopy(strict)
    lenient["dataset"]["require_generated"] = False
    report = build_datasets(lenient, **args, out=tmp_path / "lerobot", report=tmp_path / "r.json")
    assert report[FLAG] is True and report["generated_episodes"] == 0
    assert report["datasets"]["expanded"]["episodes"] == report["datasets"]["source"]["episodes"] == 1


@pytest.mark.slow
def test_a_control_arm_takes_its_own_name(tmp_path: Path, params: dict[str, Any], inputs: dict[str, Path]) -> None:
    """dataset.expanded_arm names the second dataset: the source + another store's episodes (e.g. fresh Newton ones)
    as a control arm beside the expanded one; no source-vs-expanded flag, since it is not that comparison."""
    control = copy.deepcopy(params)
    control["dataset"]["expanded_arm"] = "newton_150"
    report = build_datasets(control, **inputs, out=tmp_path / "lerobot", report=tmp_path / "r.json")
    assert sorted(report["datasets"]) == ["newton_150", "source"] and report[FLAG] is None
    assert report["datasets"]["newton_150"]["episodes"] == report["datasets"]["source"]["episodes"] + 2
    assert report["datasets"]["newton_150"]["repo_id"].endswith("/newton_150")
    assert sorted(p.name for p in (tmp_path / "lerobot").iterdir()) == ["newton_150", "source"]
    assert _load(tmp_path / "lerobot", "newton_150").num_episodes == report["datasets"]["newton_150"]["episodes"]


@pytest.mark.slow
def test_source_only_from_the_cli_h264(tmp_path: Path, inputs: dict[str, Path]) -> None:
    main(["--set", "dataset.include_expanded=false", "--set", "dataset.task=carry",
          "--set", "dataset.splits=[test]", "--set", "dataset.video_codec=h264",
          "--source-trajectories", str(inputs["source_trajectories"]), "--source-frames", str(inputs["source_frames"]),
          "--expanded-trajectories", str(tmp_path / "absent.zarr"), "--out", str(tmp_path / "lerobot"),
          "--report", str(tmp_path / "r.json")])
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["datasets"]["expanded"] is None and report["datasets"]["source"]["episodes"] == 1
    assert report[FLAG] is None  # no comparison, nothing to flag
    assert sorted(p.name for p in (tmp_path / "lerobot").iterdir()) == ["source"]
    ds = _load(tmp_path / "lerobot", "source")
    assert ds.num_episodes == 1 and ds.meta.features["observation.images.top"]["info"]["video.codec"] == "h264"
    frames = _all_frames(ds)
    check_video_frames(frames, frames["episode_index"] == 0)


def test_frame_count_mismatch_is_an_error(tmp_path: Path, inputs: dict[str, Path]) -> None:
    src = TrajectoryStore(inputs["source_trajectories"])
    short = write_frames(tmp_path / "short.zarr", src, frames={src.episode_ids[0]: T - 1})
    with pytest.raises(ValueError, match=f"{T} frames .* but {T - 1} rendered"):
        select_episodes("source", src, RenderedStore(short), "carry")


def _drop_last_frame(video: Path) -> None:
    """Re-encode `video` without its last frame (what lerobot's streaming encoder did when its queue was full)."""
    import av

    with av.open(str(video)) as src:
        frames = [f.to_ndarray(format="rgb24") for f in src.decode(video=0)]
        rate = src.streams.video[0].average_rate
    tmp = video.with_suffix(".short.mp4")
    with av.open(str(tmp), "w") as dst:
        stream = dst.add_stream("h264", rate)
        stream.width, stream.height, stream.pix_fmt = frames[0].shape[1], frames[0].shape[0], "yuv420p"
        for i, image in enumerate(frames[:-1]):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = i
            dst.mux(stream.encode(frame))
        dst.mux(stream.encode())
    tmp.replace(video)


@pytest.mark.slow
def test_a_video_that_lost_a_frame_is_named(built: dict[str, Any], tmp_path: Path) -> None:
    import shutil

    root = tmp_path / "source"
    shutil.copytree(built["out"] / "source", root)
    assert missing_video_frames(root) == []  # the stage's own dataset: every frame there
    video = sorted((root / "videos" / "observation.images.wrist").rglob("*.mp4"))[0]
    _drop_last_frame(video)
    missing = missing_video_frames(root)
    last = json.loads((root / "meta" / "info.json").read_text())["total_episodes"] - 1
    assert len(missing) == 1 and missing[0].startswith(f"{video.relative_to(root)}: episode {last} has {T - 1} of its "
                                                       f"{T} frames"), missing


def test_bad_params_name_the_key(params: dict[str, Any], inputs: dict[str, Path], tmp_path: Path) -> None:
    bad = copy.deepcopy(params)
    bad["dataset"]["video_codec"] = "mjpeg"
    with pytest.raises(ParamsError, match="dataset.video_codec"):
        build_datasets(bad, **inputs, out=tmp_path, report=tmp_path / "r.json")
    bad = copy.deepcopy(params)
    bad["dataset"]["splits"] = ["train", "holdout"]
    with pytest.raises(ParamsError, match="dataset.splits"):
        build_datasets(bad, **inputs, out=tmp_path, report=tmp_path / "r.json")
    bad = copy.deepcopy(params)
    bad["dataset"]["expanded_arm"] = "source"  # would overwrite the source dataset
    with pytest.raises(ParamsError, match="dataset.expanded_arm"):
        build_datasets(bad, **inputs, out=tmp_path, report=tmp_path / "r.json")
    bad = copy.deepcopy(params)
    bad["dataset"]["workers"] = 0
    with pytest.raises(ParamsError, match="dataset.workers"):
        build_datasets(bad, **inputs, out=tmp_path, report=tmp_path / "r.json")


def _push(root: Path, tmp_path: Path, **env: str) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k not in ("HF_TOKEN", "HUGGING_FACE_HUB_TOKEN")}
    environ.update(HF_HOME=str(tmp_path / "hf_home"), **env)  # no stored token from this machine
    return subprocess.run([sys.executable, "-m", "stages.push", str(root), "--repo-id", "user/name"],
                          capture_output=True, text=True, env=environ, timeout=120)


@pytest.mark.slow
def test_push_fails_clearly_offline(built: dict[str, Any], tmp_path: Path) -> None:
    root = built["out"] / "expanded"
    offline = _push(root, tmp_path, HF_HUB_OFFLINE="1", HF_TOKEN="hf_not_a_token")
    assert offline.returncode == 2 and offline.stderr.startswith("push: error: ")
    assert offline.stderr.strip().splitlines() == [offline.stderr.strip()]  # one line
    assert "HF_HUB_OFFLINE" in offline.stderr
    no_token = _push(root, tmp_path, HF_HUB_OFFLINE="0")
    assert no_token.returncode == 2 and "no Hugging Face token" in no_token.stderr
    with pytest.raises(PushError, match="user or org"):
        push_main([str(root), "--repo-id", "no-owner"])


def test_push_of_a_folder_that_is_no_dataset_exits_2_with_one_line(tmp_path: Path) -> None:
    """An expected error ends `stages.push` as every stage's does (README: `<stage>: error: ...`, status 2)."""
    run = _push(tmp_path, tmp_path, HF_HUB_OFFLINE="1")
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip() == f"push: error: {tmp_path} is not a LeRobot dataset (no meta/info.json); build it " \
                                 "with `python -m stages.dataset`"
    with pytest.raises(PushError, match="not a LeRobot dataset"):
        push_main([str(tmp_path), "--repo-id", "user/name"])
