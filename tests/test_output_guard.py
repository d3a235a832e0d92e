"""The session guard (tests/output_guard.py, registered by tests/conftest.py): a file created, changed or deleted
under the checkout's data/, models/ or reports/ is found by its stat fingerprint, and a pytest run whose test writes
there fails naming the paths, while a run that only reads passes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.output_guard import differences, fingerprint


def _checkout(root: Path) -> None:
    """Pipeline outputs as a checkout holds them: a report, a model file, a store's chunk, a file beside them."""
    for path, text in (("reports/train.json", "{}"), ("models/worldcontact/model.json", "{}"),
                       ("models/worldcontact/model.safetensors", "weights"),
                       ("data/source/trajectories.zarr/x/0.0", "chunk"), ("params.yaml", "a: 1")):
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_text(text)


def test_fingerprint_finds_every_kind_of_change_and_nothing_else(tmp_path):
    _checkout(tmp_path)
    before = fingerprint(tmp_path)
    assert set(before) == {"reports/train.json", "models/worldcontact/model.json", "models/worldcontact/model.safetensors",
                           "data/source/trajectories.zarr/x/0.0"}
    (tmp_path / "params.yaml").write_text("a: 2")  # outside the guarded folders
    (tmp_path / "data/source/trajectories.zarr/x/0.0").read_text()  # reading changes nothing
    assert differences(before, fingerprint(tmp_path)) == []
    chunk = tmp_path / "data/source/trajectories.zarr/x/0.0"
    stat = chunk.stat()
    chunk.write_text("CHUNK")  # same size: only the mtime tells
    os.utime(chunk, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    (tmp_path / "reports/expand.json").write_text("{}")
    (tmp_path / "models/worldcontact/model.json").unlink()
    (tmp_path / "data/expanded").mkdir()
    assert differences(before, fingerprint(tmp_path)) == [  # sorted by path
        "created data/expanded/", "changed data/source/trajectories.zarr/x/0.0", "deleted models/worldcontact/model.json",
        "created reports/expand.json"]


WRITER = '''
from tests.conftest import ROOT


def test_reads_the_outputs():
    assert (ROOT / "reports" / "train.json").read_text() == "{}"


def test_writes_the_outputs():
    (ROOT / "reports" / "expand.json").write_text("{}")
    (ROOT / "data" / "source" / "trajectories.zarr" / "x" / "0.0").write_text("overwritten")
    (ROOT / "models" / "worldcontact" / "model.json").unlink()
'''


@pytest.mark.slow
def test_a_run_that_writes_the_outputs_fails_and_names_them(tmp_path):
    """The real conftest in a copy of the checkout's tests/: the reading test's run passes, the writing test's run
    passes as a test and fails as a run."""
    _checkout(tmp_path)
    (tmp_path / "tests").mkdir()
    for name in ("__init__.py", "conftest.py", "output_guard.py"):
        shutil.copy(ROOT / "tests" / name, tmp_path / "tests" / name)
    (tmp_path / "tests" / "test_outputs.py").write_text(WRITER)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # wc from this checkout; tests (and its ROOT) from the copy

    def pytest_run(test: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                               f"tests/test_outputs.py::{test}"], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=300)

    reading = pytest_run("test_reads_the_outputs")
    assert reading.returncode == 0, reading.stdout + reading.stderr
    assert "pipeline outputs" not in reading.stdout
    writing = pytest_run("test_writes_the_outputs")
    assert writing.returncode == 1 and "1 passed" in writing.stdout, writing.stdout + writing.stderr
    summary = writing.stdout[writing.stdout.index("the tests changed the checkout's pipeline outputs"):]
    for line in ("created reports/expand.json", "changed data/source/trajectories.zarr/x/0.0",
                 "deleted models/worldcontact/model.json"):
        assert line in summary, summary
