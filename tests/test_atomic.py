"""Stale temporaries: a writer removes those a killed writer of the same target left, and nothing else."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from wc.atomic import remove_stale_temporaries, temporary_pattern
from wc.data.store import TrajectoryStore, TrajectoryWriter
from wc.reports import host_environment, save_figure_atomic, write_json_atomic, write_report_atomic


@pytest.fixture(scope="module")
def dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


@pytest.fixture(scope="module")
def live_pid() -> Iterator[int]:
    """The id of another process that is still running (a writer in flight)."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    yield child.pid
    child.kill()
    child.wait()


def _leftovers(target: Path, dead: int, live: int) -> tuple[list[Path], list[Path]]:
    """Temporaries of `target` (a file and a directory, in the writers' naming schemes) of a dead process, which
    go, and of live processes (another one, this one) and files that only look alike, which stay."""
    stale = [target.with_name(f".{target.name}.tmp-{dead}"), target.with_name(f"{target.name}.tmp-{dead}-0a1b2c3d")]
    kept = [target.with_name(f".{target.name}.tmp-{live}"), target.with_name(f"{target.name}.tmp-{live}-0a1b2c3d"),
            target.with_name(f"{target.name}.tmp-{os.getpid()}-0a1b2c3d")]
    kept += [target.with_name(n) for n in (f"{target.name}.tmp-{dead}-notes.txt", f"x{target.name}.tmp-{dead}",
                                           f"{target.name}.old-{dead}", f"{target.name}.bak")]
    for p in stale + kept:
        if p.name.endswith("-0a1b2c3d"):
            p.mkdir()
            (p / "chunk").write_text("partial")
        else:
            p.write_text("partial")
    return stale, kept


def _tiny_store(path: Path) -> None:
    with TrajectoryWriter(path, dt=0.04, substeps=1, params_hash="h", created_by="test", object_order=["cube"],
                          link_names=[], env_names=[]) as w:
        w.add_object("cube", np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros((3, 2)), np.ones(3), kind="rigid",
                     tag=1, material={})


def test_json_writer_removes_a_dead_writers_temporaries_only(tmp_path: Path, dead_pid: int, live_pid: int) -> None:
    target = tmp_path / "report.json"
    stale, kept = _leftovers(target, dead_pid, live_pid)
    write_json_atomic(target, {"a": 1})
    assert target.read_text() == '{\n  "a": 1\n}\n'
    assert not any(p.exists() for p in stale)
    assert all(p.exists() for p in kept)


def test_a_benchmark_report_writes_its_table_beside_it_atomically(tmp_path: Path, dead_pid: int,
                                                                   live_pid: int) -> None:
    target = tmp_path / "speed_cpu.json"
    stale, kept = _leftovers(target.with_suffix(".md"), dead_pid, live_pid)
    assert write_report_atomic(target, {"a": 1}, "| a |\n") == target
    assert target.read_text() == '{\n  "a": 1\n}\n' and target.with_suffix(".md").read_text() == "| a |\n"
    assert not any(p.exists() for p in stale) and all(p.exists() for p in kept)


def test_a_run_over_several_gpus_names_their_count_beside_the_model(monkeypatch: pytest.MonkeyPatch) -> None:
    import wc.reports

    monkeypatch.setattr(wc.reports, "environment_info", lambda device: {"device": device, "gpu": "NVIDIA H200"}
                        if device.startswith("cuda") else {"device": device})
    assert host_environment("cuda", 2) == {"device": "cuda", "gpu": "2 x NVIDIA H200"}
    assert host_environment("cpu", 0) == {"device": "cpu"}


def test_store_writer_removes_a_dead_writers_temporaries_only(tmp_path: Path, dead_pid: int, live_pid: int) -> None:
    target = tmp_path / "raw.zarr"
    stale, kept = _leftovers(target, dead_pid, live_pid)
    old = target.with_name(f"{target.name}.tmp-old-{dead_pid}-0a1b2c3d")
    old.mkdir()
    _tiny_store(target)
    assert TrajectoryStore(target).object_names == ["cube"]
    assert not any(p.exists() for p in [*stale, old])
    assert all(p.exists() for p in kept)


def test_figure_temporary_keeps_its_suffix_and_is_removed(tmp_path: Path, dead_pid: int) -> None:
    from wc.reports import pyplot

    target = tmp_path / "curve.png"
    stale = tmp_path / f".curve.png.tmp-{dead_pid}.png"
    stale.write_bytes(b"partial")
    save_figure_atomic(pyplot().figure(), target)
    assert target.read_bytes().startswith(b"\x89PNG") and not stale.exists()


def test_pattern_and_missing_directory(tmp_path: Path) -> None:
    pattern = temporary_pattern(Path("out/policy"))
    names = [".policy.tmp-12", ".policy.tmp-12-ab12", "policy.tmp-12-ab12", "policy.tmp-old-12-ab12",
             ".policy.old-12-ab12"]
    assert all(pattern.fullmatch(n)["pid"] == "12" for n in names)
    assert not any(pattern.fullmatch(n) for n in ["policy", "policy.tmp-", "policy2.tmp-12", ".policy.tmp-12.zip"])
    assert remove_stale_temporaries(tmp_path / "absent" / "x.json") == []
