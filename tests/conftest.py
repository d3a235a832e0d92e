"""What many test modules share: the repository root, the shipped params with small overrides, the default scene
config and synthetic trajectory stores in temporary directories.

Tests that run Newton (simulator, renderer, kinematics), a whole stage or a stage subprocess, or that take more than
a few seconds on a 2-core CPU carry the `slow` marker (pyproject.toml); `pytest -m "not slow"` runs the rest.

A test writes only into its temporary directories: the run fails, naming the paths, when anything under the checkout's
data/, models/ or reports/ was created, changed or deleted (tests/output_guard.py)."""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from tests.output_guard import OutputGuard
from wc.config import load_section, read_params
from wc.scene.config import SceneConfig

ROOT = Path(__file__).resolve().parents[1]


def pytest_configure(config: pytest.Config) -> None:
    """Fingerprint the checkout's pipeline outputs now; compared when the session ends (tests/output_guard.py)."""
    config.pluginmanager.register(OutputGuard(ROOT), "output_guard")


def load_params(*overrides: str, file: str = "params.yaml") -> dict[str, Any]:
    """A shipped params file (`file`, relative to the repository root) with `key.sub=value` overrides; training from
    scratch (`train.init_from` ""), as the tests' small models need, unless an override names a checkpoint."""
    return read_params(ROOT / file, ["train.init_from=''", *overrides])


def default_params(train: dict[str, Any] | None = None) -> dict[str, Any]:
    """params.yaml with the `train` section updated by `train` (a tiny schedule for tests)."""
    params = load_params()
    params["train"].update(copy.deepcopy(train or {}))
    return params


@pytest.fixture(scope="session")
def scene_cfg() -> SceneConfig:
    """The scene section of params.yaml (frozen: safe to share)."""
    return load_section(load_params(), "scene", SceneConfig)


SyntheticStore = Callable[..., Path]


@pytest.fixture(scope="session")
def synthetic_store(tmp_path_factory: pytest.TempPathFactory) -> SyntheticStore:
    """write_synthetic_store into a fresh temporary directory: (params, episodes, frames=12, seed=0) -> its path."""
    from tests.synthetic_store import write_synthetic_store  # on use: it imports the scene stack (~10 s)

    def write(params: dict[str, Any], episodes: Sequence[tuple[str, str]], frames: int = 12, seed: int = 0) -> Path:
        return write_synthetic_store(tmp_path_factory.mktemp("store") / "s.zarr", params, list(episodes), frames, seed)

    return write


@pytest.fixture(scope="session")
def local_ray() -> Iterator[None]:
    """A Ray instance on this machine with two CPUs (two workers at once) for the ray executor's tests, which the
    stages use as it is (wc.distributed.open_executor); shut down after the last test."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, runtime_env={"env_vars": {"PYTHONPATH": str(ROOT)}})
    yield
    ray.shutdown()
