"""Render stage: shapes, the bag where it projects, the wrist camera riding on the arm, atomic output,
clear errors. Tiny synthetic stores at 32 x 32 px."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import zarr

from tests.conftest import SyntheticStore, load_params
from tests.synthetic_store import write_synthetic_store
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.render.frames import RenderedStore
from wc.render.geometry import episode_geometry
from wc.render.renderer import EpisodeRenderer
from wc.render.rig import render_cameras
from wc.render.stage import render
from wc.scene.cameras import camera_pose, intrinsics
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene

SIZE = 32


@pytest.fixture(scope="module")
def params() -> dict:
    p = load_params()
    p["render"].update(width=SIZE, height=SIZE, frames_per_batch=4, tasks=None, sheet_frames=3)
    return p


@pytest.fixture(scope="module")
def store(params: dict, synthetic_store: SyntheticStore) -> Path:
    return synthetic_store(params, [("carry", "train"), ("handoff", "test")], frames=6)


def _renderer(params: dict, store: Path, eid: str) -> tuple[EpisodeRenderer, TrajectoryStore, SceneConfig]:
    scene_cfg = load_section(params, "scene", SceneConfig)
    src = TrajectoryStore(store)
    cams = render_cameras(scene_cfg.cameras, ["top", "wrist"], SIZE, SIZE)
    return EpisodeRenderer(episode_geometry(src, eid, scene_cfg), cams, "cpu", 4, True), src, scene_cfg


@pytest.mark.slow
def test_stage_writes_frames_report_and_sheet(params: dict, store: Path, tmp_path: Path) -> None:
    out, report, sheet = tmp_path / "rendered.zarr", tmp_path / "render.json", tmp_path / "sheet.png"
    result = render(params, [(store, out)], report, sheet)
    frames = RenderedStore(out)
    src = TrajectoryStore(store)
    assert frames.cameras == ["top", "wrist"] and frames.episode_ids() == src.episode_ids
    assert frames.attrs["fps"] == pytest.approx(1.0 / src.dt)
    for eid in src.episode_ids:
        assert frames.episode_attrs(eid)["task"] == src.episode_attrs(eid)["task"]
        for cam in frames.cameras:
            a = frames.frames(eid, cam)
            assert a.dtype == np.uint8 and a.shape == (src.num_frames(eid), SIZE, SIZE, 3)
            assert a.reshape(-1, 3).std(axis=0).max() > 5  # not a blank image
    assert result["frames"] == sum(src.num_frames(e) for e in src.episode_ids)
    assert set(result["ms_per_frame"]) == {"top", "wrist"} and report.is_file() and sheet.stat().st_size > 0

    only = copy.deepcopy(params)
    only["render"]["tasks"] = ["handoff"]
    render(only, [(store, out)], report, sheet)
    assert [RenderedStore(out).episode_attrs(e)["task"] for e in RenderedStore(out).episode_ids()] == ["handoff"]
    only["render"]["tasks"] = ["no_such_task"]
    with pytest.raises(ValueError, match="no episode to render"):
        render(only, [(store, tmp_path / "none.zarr")], report, sheet)
    # an expansion that accepted nothing: an empty store renders to an empty frames store, not an error
    empty = write_synthetic_store(tmp_path / "empty.zarr", params, [], frames=6)
    result = render(only | {"render": params["render"]}, [(store, tmp_path / "again.zarr"),
                                                          (empty, tmp_path / "empty_frames.zarr")], report, sheet)
    assert result["outputs"][1]["episodes"] == 0 and RenderedStore(tmp_path / "empty_frames.zarr").episode_ids() == []


@pytest.mark.slow
def test_bag_is_drawn_where_it_projects(params: dict, store: Path) -> None:
    renderer, src, scene_cfg = _renderer(params, store, "ep_000000")
    a = src.read_episode("ep_000000", ("x", "link_poses"))
    x, poses = a["x"][:1] + np.array([0.12, 0.08, 0.0], np.float32), a["link_poses"][:1]  # off-centre: a flip shows
    with_bag = renderer.render(x, poses)["top"][0].astype(int)
    without = renderer.render(x + np.array([0.0, 0.0, -5.0], np.float32), poses)["top"][0].astype(int)
    cam = renderer.cameras["top"]
    eye, rot = camera_pose(cam, tuple(src.episode_links("ep_000000")), poses[0])
    bag = x[0, src.episode_layout("ep_000000")["bag"]]
    p = min((rot.T @ (v - eye) for v in bag), key=lambda q: -q[2])  # nearest vertex (camera frame, looking along -z)
    u, v, _ = intrinsics(cam) @ np.array([p[0], -p[1], -p[2]]) / -p[2]
    row, col = int(v), int(u)
    assert 0 <= row < SIZE and 0 <= col < SIZE
    patch = (slice(max(row - 1, 0), row + 2), slice(max(col - 1, 0), col + 2))
    diff = np.abs(with_bag[patch] - without[patch]).sum(axis=-1)
    assert diff.max() > 60, f"bag pixel at ({row}, {col}) looks like the background: {with_bag[row, col]}"
    r, g, b = with_bag[patch].reshape(-1, 3)[diff.reshape(-1).argmax()]
    assert r > b + 30  # the light fabric colour, not the grey robot or the blue wall


@pytest.mark.slow
def test_wrist_view_follows_the_right_arm(params: dict, store: Path) -> None:
    renderer, src, scene_cfg = _renderer(params, store, "ep_000000")
    x = src.read_episode("ep_000000", ("x",))["x"][:1].repeat(3, axis=0)
    scene = build_scene(scene_cfg, ["bag"])
    actions = np.repeat(scene.home_action()[None], 3, axis=0)
    actions[1, 5] += 0.4  # left wrist roll: the right wrist camera stays put (the left arm barely changes shape)
    actions[2, 7] += 0.4  # right shoulder yaw
    links = src.episode_links("ep_000000")
    poses = scene.link_poses(actions)[:, [list(scene.link_names).index(n) for n in links]]
    wrist = renderer.render(x, poses)["wrist"].astype(int)
    assert np.abs(wrist[2] - wrist[0]).mean() > 3 * np.abs(wrist[1] - wrist[0]).mean() + 1


@pytest.mark.slow
def test_output_is_atomic_on_error(params: dict, store: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken.zarr"
    write_synthetic_store(broken, params, [("fall", "train"), ("carry", "train")], frames=6)
    out = tmp_path / "rendered.zarr"
    render(params, [(broken, out)], tmp_path / "r.json", tmp_path / "s.png")
    before = RenderedStore(out).frames("ep_000001", "top")
    x = zarr.open_group(broken / "episodes" / "ep_000001", mode="r+")["x"]
    x[2] = np.nan  # a corrupt second episode: fails after the first was written
    with pytest.raises(ValueError, match="corrupt"):
        render(params, [(broken, out)], tmp_path / "r.json", tmp_path / "s.png")
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("rendered")) == ["rendered.zarr"]
    np.testing.assert_array_equal(RenderedStore(out).frames("ep_000001", "top"), before)


def test_clear_errors(params: dict, store: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not found"):
        render(params, [(tmp_path / "missing.zarr", tmp_path / "out.zarr")], tmp_path / "r.json", tmp_path / "s.png")
    bad = copy.deepcopy(params)
    bad["scene"]["cameras"]["wrist"]["link"] = "right_link9"
    with pytest.raises(ValueError, match="right_link9"):
        render(bad, [(store, tmp_path / "out.zarr")], tmp_path / "r.json", tmp_path / "s.png")
    assert not (tmp_path / "out.zarr").exists()
    bad = copy.deepcopy(params)
    bad["render"]["cameras"] = ["top", "side"]
    with pytest.raises(ParamsError, match="side"):
        render(bad, [(store, tmp_path / "out.zarr")], tmp_path / "r.json", tmp_path / "s.png")
    bad = copy.deepcopy(params)
    bad["render"]["width"] = 0
    with pytest.raises(ParamsError, match="width"):
        render(bad, [(store, tmp_path / "out.zarr")], tmp_path / "r.json", tmp_path / "s.png")
