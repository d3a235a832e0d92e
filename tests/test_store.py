"""Trajectory store: schema, round trip, chunked reads, atomic writes, corruption, segments."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import zarr
from torch.utils.data import DataLoader
from zarr.codecs import ZstdCodec
from zarr.storage import LocalStore

from wc.train.data import LayoutBatchSampler, WindowDataset, phases_of, windows_of
from wc.data.store import (
    EPISODE_ARRAYS, SCHEMA, TrajectoryStore, TrajectoryWriter, copy_store,
)

N_BAG, N_CUBE = 6, 4
N = N_BAG + N_CUBE
LINKS = ["right_link6", "right_finger_a", "held_cube"]
ENVS = ["table"]


def _scene() -> dict[str, Any]:
    rng = np.random.default_rng(0)
    return {
        "bag": dict(rest_positions=rng.normal(size=(N_BAG, 3)), faces=np.array([[0, 1, 2], [3, 4, 5]]),
                    rest_uv=rng.uniform(size=(N_BAG, 2)), vertex_area=rng.uniform(size=N_BAG),
                    kind="cloth", tag=1, material={"stretch_ke": 1e4, "density_kg_m2": 0.2}),
        "cube": dict(rest_positions=rng.normal(size=(N_CUBE, 3)), faces=np.array([[0, 1, 2], [1, 2, 3]]),
                     rest_uv=np.zeros((N_CUBE, 2)), vertex_area=np.full(N_CUBE, 0.01),
                     kind="rigid", tag=2, material={"mass_kg": 0.1}),
    }


def _episode(T: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return dict(x=rng.normal(size=(T, N, 3)), v=rng.normal(size=(T, N, 3)), action=rng.normal(size=(T, 14)),
                link_poses=rng.normal(size=(T, len(LINKS), 7)), env_poses=rng.normal(size=(T, len(ENVS), 7)))


def _attrs(i: int, split: str | None = "train", task: str = "lift") -> dict[str, Any]:
    return dict(task=task, seed=100 + i, cell=[i, 0], speed=0.5, amplitude=0.1, split=split,
                accepted=True, first_failure=None, source="simulator")


def _writer(path: Path, chunk_frames: int = 16, write_processes: int = 0) -> TrajectoryWriter:
    return TrajectoryWriter(path, dt=0.04, substeps=20, params_hash="abc123", created_by="test",
                            object_order=["bag", "cube"], link_names=LINKS, env_names=ENVS,
                            chunk_frames=chunk_frames, write_processes=write_processes)


def _add_scene(w: TrajectoryWriter) -> None:
    for name, o in _scene().items():
        w.add_object(name, **o)
    w.add_prescribed("table", np.ones((5, 3)), np.tile([0.0, 0.0, 1.0], (5, 1)), tag=3, link="table")
    w.add_prescribed("right_finger_a", np.zeros((2, 3)), np.ones((2, 3)), tag=4, link="right_finger_a")


def _make_store(path: Path, lengths=(40, 3, 20), splits=("train", "val", "train"), chunk_frames: int = 16,
                write_processes: int = 0):
    episodes = []
    with _writer(path, chunk_frames, write_processes) as w:
        _add_scene(w)
        for i, (T, split) in enumerate(zip(lengths, splits)):
            ep = _episode(T, seed=i)
            eid = w.add_episode(**ep, **_attrs(i, split))
            episodes.append((eid, ep))
    return episodes


def _leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if ".tmp-" in p.name)


def test_round_trip_and_schema(tmp_path: Path) -> None:
    path = tmp_path / "raw.zarr"
    episodes = _make_store(path)
    s = TrajectoryStore(path)
    a = s.attrs
    assert a["schema"] == SCHEMA and a["dt"] == 0.04 and a["substeps"] == 20 and a["units"] == "m, s"
    assert a["created_by"] == "test" and a["params_hash"] == "abc123"
    assert a["object_order"] == ["bag", "cube"] and a["object_offsets"] == [0, N_BAG, N]
    assert s.link_names == LINKS and s.env_names == ENVS and a["prescribed_order"] == ["table", "right_finger_a"]
    for name, o in _scene().items():
        got = s.objects[name]
        np.testing.assert_array_equal(got.rest_positions, o["rest_positions"].astype(np.float32))
        np.testing.assert_array_equal(got.faces, o["faces"])
        np.testing.assert_array_equal(got.rest_uv, o["rest_uv"].astype(np.float32))
        np.testing.assert_array_equal(got.vertex_area, o["vertex_area"].astype(np.float32))
        assert got.faces.dtype == np.int32 and got.rest_positions.dtype == np.float32
        assert (got.kind, got.tag, got.material) == (o["kind"], o["tag"], o["material"])
    assert s.objects["cube"].vertices == slice(N_BAG, N)
    p = s.prescribed["table"]
    assert p.link == "table" and p.tag == 3 and p.local_points.shape == (5, 3)
    np.testing.assert_array_equal(p.local_normals, np.tile([0, 0, 1], (5, 1)).astype(np.float32))
    assert list(s.prescribed) == ["table", "right_finger_a"]
    assert s.episode_ids == ["ep_000000", "ep_000001", "ep_000002"]
    for i, (eid, ep) in enumerate(episodes):
        got = s.read_episode(eid)
        for k in EPISODE_ARRAYS:
            assert got[k].dtype == np.float32
            np.testing.assert_array_equal(got[k], ep[k].astype(np.float32))
        assert s.episode_attrs(eid) == _attrs(i, ["train", "val", "train"][i])
        assert s.num_frames(eid) == len(ep["x"])
    assert s.episodes_where(split="train") == ["ep_000000", "ep_000002"]
    assert s.episodes_where(split="val", task="lift", accepted=True) == ["ep_000001"]
    assert s.episodes_where(task="push") == []


def test_chunks_compression_and_window_reads(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "s.zarr"
    (eid, ep), *_ = _make_store(path, chunk_frames=8)
    s = TrajectoryStore(path)
    arrays = s._episode_arrays(eid)
    for k, a in arrays.items():
        assert a.chunks[0] == 8 and a.chunks[1:] == a.shape[1:], k
        assert any(isinstance(c, ZstdCodec) for c in a.compressors), k
    assert s.chunk_frames(eid) == 8
    assert len(list((path / "episodes" / eid / "x" / "c").iterdir())) == 5  # 40 frames / 8

    keys: list[str] = []
    orig = LocalStore.get

    async def counting_get(self, key, *args, **kwargs):  # type: ignore[no-untyped-def]
        keys.append(key)
        return await orig(self, key, *args, **kwargs)

    monkeypatch.setattr(LocalStore, "get", counting_get)
    win = s.read_window(eid, 17, 5)  # frames 17..21: chunk 2 only
    for k in EPISODE_ARRAYS:
        np.testing.assert_array_equal(win[k], ep[k][17:22].astype(np.float32))
    chunk_keys = {key for key in keys if "/c/" in key}
    assert chunk_keys == {f"episodes/{eid}/{k}/c/2/0" + ("/0" if k != "action" else "") for k in EPISODE_ARRAYS}
    keys.clear()
    s.read_window(eid, 6, 5, fields=("x",))  # frames 6..10 straddle chunks 0 and 1
    assert {key for key in keys if "/c/" in key} == {f"episodes/{eid}/x/c/0/0/0", f"episodes/{eid}/x/c/1/0/0"}

    with pytest.raises(IndexError, match="out of range"):
        s.read_window(eid, 38, 5)
    with pytest.raises(IndexError, match="out of range"):
        s.read_window(eid, -1, 5)
    with pytest.raises(KeyError, match="ep_000099"):
        s.read_window("ep_000099", 0, 5)


def test_nan_rejected_and_nothing_written(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    ep = _episode(10)
    ep["x"][7, 3, 1] = np.nan
    with pytest.raises(ValueError, match=r"episode ep_000000.*'x'.*index 7"):
        with _writer(path) as w:
            _add_scene(w)
            w.add_episode(**ep, **_attrs(0))
    assert not path.exists() and _leftovers(tmp_path) == []


@pytest.mark.parametrize("bad, match", [
    (dict(x=np.zeros((10, N + 1, 3))), r"'x' has shape \(10, 11, 3\), expected \(10, 10, 3\)"),
    (dict(action=np.zeros((9, 14))), r"'action' has shape \(9, 14\)"),
    (dict(link_poses=np.zeros((10, 2, 7))), "'link_poses'"),
    (dict(v=np.full((10, N, 3), "a")), "dtype"),
    (dict(env_poses=np.full((10, 1, 7), np.inf)), "'env_poses'.*non-finite"),
])
def test_episode_validation(tmp_path: Path, bad: dict[str, Any], match: str) -> None:
    with pytest.raises((ValueError, TypeError), match=match):
        with _writer(tmp_path / "s.zarr") as w:
            _add_scene(w)
            w.add_episode(**{**_episode(10), **bad}, **_attrs(0))
    assert _leftovers(tmp_path) == []


def test_attr_and_scene_validation(tmp_path: Path) -> None:
    with _writer(tmp_path / "s.zarr") as w:
        with pytest.raises(RuntimeError, match="add_object"):
            w.add_episode(**_episode(3), **_attrs(0))
        with pytest.raises(ValueError, match="faces index vertices outside"):
            w.add_object("bag", **{**_scene()["bag"], "faces": np.array([[0, 1, 6]])})
        _add_scene(w)
        with pytest.raises(ValueError, match=r"missing required attrs \['first_failure'\]"):
            w.add_episode(**_episode(3), **{k: v for k, v in _attrs(0).items() if k != "first_failure"})
        with pytest.raises(ValueError, match="split 'dev'"):
            w.add_episode(**_episode(3), **{**_attrs(0), "split": "dev"})
        with pytest.raises(ValueError, match="link 'nowhere'"):
            w.add_prescribed("p", np.zeros((1, 3)), np.zeros((1, 3)), tag=0, link="nowhere")
        eid = w.add_episode(**_episode(3), **{**_attrs(0), "split": None, "seed": np.int64(5)})
    assert TrajectoryStore(tmp_path / "s.zarr").episode_attrs(eid)["seed"] == 5
    with pytest.raises(ValueError, match=r"objects \['cube'\] in object_order were never added"):
        with _writer(tmp_path / "t.zarr") as w:
            w.add_object("bag", **_scene()["bag"])
    assert not (tmp_path / "t.zarr").exists() and _leftovers(tmp_path) == []


def test_exception_in_with_leaves_nothing_and_replace_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    with pytest.raises(RuntimeError, match="boom"):
        with _writer(path) as w:
            _add_scene(w)
            w.add_episode(**_episode(5), **_attrs(0))
            raise RuntimeError("boom")
    assert not path.exists() and _leftovers(tmp_path) == []
    _make_store(path, lengths=(5,), splits=("train",))
    with pytest.raises(RuntimeError, match="boom"):  # a failed rewrite keeps the old store
        with _writer(path) as w:
            raise RuntimeError("boom")
    assert TrajectoryStore(path).episode_ids == ["ep_000000"]
    _make_store(path, lengths=(5, 6), splits=("train", "val"))  # a successful one replaces it
    assert TrajectoryStore(path).episode_ids == ["ep_000000", "ep_000001"] and _leftovers(tmp_path) == []
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "a.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not a zarr store"):
        with _writer(tmp_path / "notes"):
            pass
    assert (tmp_path / "notes" / "a.txt").exists()


def test_write_processes_write_the_same_store_and_a_failed_write_leaves_nothing(tmp_path: Path) -> None:
    """Episodes checked here and written by two processes: the same ids, arrays and attrs as written in this process;
    a write that fails in a process fails the writer, and no store or temporary folder is left."""
    here = _make_store(tmp_path / "here.zarr", lengths=(7, 3, 5, 9))
    _make_store(tmp_path / "there.zarr", lengths=(7, 3, 5, 9), write_processes=2)
    a, b = TrajectoryStore(tmp_path / "here.zarr"), TrajectoryStore(tmp_path / "there.zarr")
    assert a.episode_ids == b.episode_ids == [eid for eid, _ in here]
    for eid, ep in here:
        assert a.episode_attrs(eid) == b.episode_attrs(eid)
        got = b.read_episode(eid, tuple(ep))
        for k, arr in ep.items():
            np.testing.assert_array_equal(got[k], arr.astype(np.float32))
    path = tmp_path / "failed.zarr"
    with pytest.raises(OSError):
        with _writer(path, write_processes=1) as w:
            _add_scene(w)
            (w._tmp / "episodes" / "ep_000000").write_text("in the way")  # a file where the episode's folder goes
            w.add_episode(**_episode(5), **_attrs(0))
    assert not path.exists() and _leftovers(tmp_path) == []


def test_unwritable_output(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "file").write_text("")
    with pytest.raises(OSError, match=str(tmp_path / "file" / "s.zarr")):
        with _writer(tmp_path / "file" / "s.zarr"):
            pass
    ro = tmp_path / "ro"
    ro.mkdir()
    real_mkdir = os.mkdir

    def deny(p, *args, **kwargs):  # type: ignore[no-untyped-def]
        if Path(p).parent == ro:
            raise PermissionError(13, "Permission denied", str(p))
        return real_mkdir(p, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", deny)  # chmod does not stop root, so simulate it
    with pytest.raises(PermissionError, match=f"cannot write trajectory store {ro / 's.zarr'}.*not writable"):
        with _writer(ro / "s.zarr"):
            pass
    assert list(ro.iterdir()) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permissions")
def test_readonly_directory(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(PermissionError, match="not writable"):
            with _writer(ro / "s.zarr"):
                pass
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o700)


def test_missing_or_corrupt_store(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no trajectory store"):
        TrajectoryStore(tmp_path / "missing.zarr")
    (tmp_path / "empty.zarr").mkdir()
    with pytest.raises(ValueError, match="not a worldcontact trajectory store"):
        TrajectoryStore(tmp_path / "empty.zarr")
    path = tmp_path / "s.zarr"
    _make_store(path, lengths=(40,), splits=("train",), chunk_frames=8)
    root = zarr.open_group(path, mode="r+")
    root.attrs["schema"] = "worldcontact-trajectories/0"
    with pytest.raises(ValueError, match="version mismatch"):
        TrajectoryStore(path)
    del root.attrs["schema"]
    with pytest.raises(ValueError, match=f"{path} is not a worldcontact trajectory store"):
        TrajectoryStore(path)
    root.attrs["schema"] = SCHEMA
    shutil.rmtree(path / "episodes" / "ep_000000" / "v" / "c" / "2")  # a lost chunk reads as NaN fill
    with pytest.raises(ValueError, match=r"corrupt episode ep_000000: array 'v'.*missing chunk"):
        TrajectoryStore(path).read_window("ep_000000", 16, 5)
    TrajectoryStore(path).read_window("ep_000000", 0, 5)  # untouched chunks still read
    shutil.rmtree(path / "episodes" / "ep_000000" / "action")
    with pytest.raises(ValueError, match="'episodes/ep_000000/action' is missing"):
        TrajectoryStore(path).read_episode("ep_000000")
    shutil.rmtree(path / "objects" / "cube")
    with pytest.raises(ValueError, match="'objects/cube' is missing"):
        TrajectoryStore(path).objects


def test_copy_store_subset_with_updates(tmp_path: Path) -> None:
    episodes = _make_store(tmp_path / "raw.zarr", splits=(None, None, None))
    src = TrajectoryStore(tmp_path / "raw.zarr")
    dst = copy_store(src, tmp_path / "val.zarr", ["ep_000000", "ep_000002"],
                     {"ep_000000": {"split": "train"}, "ep_000002": {"split": "test", "accepted": True}},
                     params_hash="def456")
    assert dst.episode_ids == ["ep_000000", "ep_000002"] and dst.attrs["params_hash"] == "def456"
    assert dst.episode_attrs("ep_000002")["split"] == "test" and dst.episodes_where(split="train") == ["ep_000000"]
    np.testing.assert_array_equal(dst.read_episode("ep_000002")["x"], episodes[2][1]["x"].astype(np.float32))
    assert dst.objects["bag"].material == src.objects["bag"].material and list(dst.prescribed) == list(src.prescribed)
    assert dst.chunk_frames("ep_000000") == 16
    with pytest.raises(ValueError, match="split 'bogus'"):
        copy_store(src, tmp_path / "bad.zarr", ["ep_000001"], {"ep_000001": {"split": "bogus"}})
    assert not (tmp_path / "bad.zarr").exists() and _leftovers(tmp_path) == []


def test_training_windows_and_layout_sampler(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    _make_store(path)  # T = 40 (train), 3 (val), 20 (train)
    s = TrajectoryStore(path)
    windows = windows_of(phases_of(s, "train"), 5)
    assert len(windows) == (40 - 4) + (20 - 4)
    assert {w.phase.episode for w in windows} == {"ep_000000", "ep_000002"}
    assert all(0 <= w.start <= s.num_frames(w.phase.episode) - 5 for w in windows)
    def first_batches(seed: int) -> list[list[int]]:
        batches = iter(LayoutBatchSampler(windows, 3, seed))
        return [next(batches) for _ in range(4)]
    assert first_batches(7) == first_batches(7) != first_batches(8)
    assert len(windows_of(phases_of(s, "val"), 3)) == 1
    assert windows_of(phases_of(s, "val"), 5) == []  # the only val episode has 3 frames


def test_window_dataset_dataloader(tmp_path: Path) -> None:
    path = tmp_path / "s.zarr"
    episodes = dict(_make_store(path))
    ds = WindowDataset(path, windows_of(phases_of(TrajectoryStore(path), "train"), 5), 5)
    w = ds.windows[3]
    item = ds[3]
    assert item["x"].dtype == torch.float32
    torch.testing.assert_close(item["v"], torch.from_numpy(episodes[w.phase.episode]["v"][w.start:w.start + 5]
                                                           .astype(np.float32)))
    loader = DataLoader(ds, batch_size=4, num_workers=2, shuffle=True, generator=torch.Generator().manual_seed(0))
    batches = list(loader)
    assert sum(len(b["x"]) for b in batches) == len(ds) == 52
    b = batches[0]
    assert b["x"].shape == (4, 5, N, 3) and b["action"].shape == (4, 5, 14)
    assert b["poses"].shape == (4, 5, len(LINKS) + len(ENVS), 7)

def test_episode_with_a_subset_of_objects_and_links(tmp_path: Path) -> None:
    """An episode may hold only some objects and link columns; the reader returns its layout."""
    full = _episode(4)
    ep = dict(full, x=full["x"][:, :N_BAG], v=full["v"][:, :N_BAG], link_poses=full["link_poses"][:, :2])
    layout = dict(objects=["bag"], links=LINKS[:2])
    with _writer(tmp_path / "s.zarr") as w:
        _add_scene(w)
        eid = w.add_episode(**ep, **layout, **_attrs(0))
        with pytest.raises(ValueError, match="must follow the store's order"):
            w.add_episode(**full, objects=["cube", "bag"], **_attrs(1))
        with pytest.raises(ValueError, match="not in the store"):
            w.add_episode(**full, links=["left_link6"], **_attrs(1))
        with pytest.raises(ValueError, match="x"):
            w.add_episode(**full, **layout, **_attrs(1))  # x still holds the cube's rows
        w.add_episode(**full, **_attrs(2))  # no layout attrs: every object and link
    s = TrajectoryStore(tmp_path / "s.zarr")
    assert s.episode_objects(eid) == ["bag"] and s.episode_links(eid) == LINKS[:2]
    assert s.episode_layout(eid) == {"bag": slice(0, N_BAG)}
    got = s.read_episode(eid)
    assert got["x"].shape == (4, N_BAG, 3) and got["link_poses"].shape == (4, 2, 7)
    np.testing.assert_allclose(got["x"], ep["x"].astype(np.float32))
    last = s.episode_ids[-1]
    assert s.episode_layout(last) == {"bag": slice(0, N_BAG), "cube": slice(N_BAG, N)}
