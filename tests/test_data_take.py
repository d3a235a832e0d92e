"""`python -m wc.data.take`: N episodes of a store, after a skip, of one task, accepted only by default."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT
from tests.test_store import _add_scene, _attrs, _episode, _writer
from wc.data.store import TrajectoryStore
from wc.data.take import main, take

# (task, accepted) of ep_000000 .. ep_000005: lift's accepted episodes are 0, 3, 4, 5
EPISODES = [("lift", True), ("lift", False), ("poke", True), ("lift", True), ("lift", True), ("lift", True)]


@pytest.fixture()
def store(tmp_path: Path) -> Path:
    path = tmp_path / "newton.zarr"
    with _writer(path) as w:
        _add_scene(w)
        for i, (task, accepted) in enumerate(EPISODES):
            w.add_episode(**_episode(5, seed=i), **{**_attrs(i, task=task), "accepted": accepted})
    return path


def test_take_the_first_n_then_the_next_after_a_skip(store: Path, tmp_path: Path) -> None:
    first = take(store, tmp_path / "source.zarr", 2, task="lift")
    rest = take(store, tmp_path / "extra.zarr", 2, skip=2, task="lift")
    assert TrajectoryStore(tmp_path / "source.zarr").episode_ids == ["ep_000000", "ep_000003"]
    assert TrajectoryStore(tmp_path / "extra.zarr").episode_ids == ["ep_000004", "ep_000005"]
    assert first["matching"] == rest["matching"] == 4 and rest["taken"] == 2
    src, out = TrajectoryStore(store), TrajectoryStore(tmp_path / "source.zarr")
    np.testing.assert_array_equal(out.read_episode("ep_000003")["x"], src.read_episode("ep_000003")["x"])
    assert out.episode_attrs("ep_000003") == src.episode_attrs("ep_000003")


def test_rejected_episodes_only_on_request(store: Path, tmp_path: Path) -> None:
    take(store, tmp_path / "all.zarr", 3, task="lift", accepted_only=False)
    assert TrajectoryStore(tmp_path / "all.zarr").episode_ids == ["ep_000000", "ep_000001", "ep_000003"]
    take(store, tmp_path / "any_task.zarr", 2, skip=1)
    assert TrajectoryStore(tmp_path / "any_task.zarr").episode_ids == ["ep_000002", "ep_000003"]


def test_too_few_is_an_error_unless_at_most(store: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="4 accepted episodes of lift, 1 after skipping 3: fewer than the 2"):
        take(store, tmp_path / "short.zarr", 2, skip=3, task="lift")
    assert not (tmp_path / "short.zarr").exists()
    assert main([str(store), str(tmp_path / "short.zarr"), "-n", "2", "--skip", "3", "--task", "lift",
                 "--at-most"])["taken"] == 1
    with pytest.raises(ValueError, match="0 after skipping 4"):
        take(store, tmp_path / "none.zarr", 1, skip=4, task="lift", at_most=True)


def test_command_line_errors_are_one_line_with_status_2(store: Path, tmp_path: Path) -> None:
    for args, message in [([str(store), str(tmp_path / "o.zarr"), "-n", "9"], "fewer than the 9 asked for"),
                          ([str(tmp_path / "missing.zarr"), str(tmp_path / "o.zarr"), "-n", "1"], "no such store")]:
        run = subprocess.run([sys.executable, "-m", "wc.data.take", *args], cwd=ROOT, capture_output=True, text=True)
        assert run.returncode == 2 and run.stderr.startswith("take: error: ") and message in run.stderr, run.stderr
        assert len(run.stderr.strip().splitlines()) == 1
