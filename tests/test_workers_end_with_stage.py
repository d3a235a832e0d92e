"""Processes a stage starts end with it when it is killed (kill -9): its worker pool's processes (wc.worker_pool:
parent-death signal and a watcher thread) and a local Ray instance's raylet, agents and workers (wc.reaper). The
stage tests start a real `python -m stages.simulate`, wait for its workers, kill it and look for survivors."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import psutil
import pytest

from tests.conftest import ROOT
from wc.worker_pool import WATCHER_NAME

GONE_WITHIN_S = 30.0  # the watcher threads poll every 0.5 s, the reaper every 0.2 s; Ray's agents notice a dead raylet
# later (a DashboardAgent once outlived 10 s on a loaded 2-core CPU); the rest is a loaded CPU


def _alive(processes: list[psutil.Process]) -> list[str]:
    """What still runs among `processes` (zombies count as gone)."""
    out = []
    for p in processes:
        try:
            if p.status() != psutil.STATUS_ZOMBIE:
                out.append(f"{p.pid} {' '.join(p.cmdline())[:120]}")
        except psutil.NoSuchProcess:
            pass
    return out


def _kill_and_wait(parent: subprocess.Popen, processes: list[psutil.Process]) -> list[str]:
    """kill -9 `parent`; what of `processes` still runs GONE_WITHIN_S later (empty as soon as none does)."""
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + GONE_WITHIN_S
    while (alive := _alive(processes)) and time.monotonic() < deadline:
        time.sleep(0.2)
    return alive


def _python(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def _wait_for(parent: subprocess.Popen, ready: Callable[[list[psutil.Process]], bool], timeout_s: float
              ) -> list[psutil.Process]:
    """`parent`'s descendants once `ready(descendants)` holds (fails if it exits first or `timeout_s` passes)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert parent.poll() is None, f"the stage ended first (status {parent.returncode})"
        try:
            descendants = psutil.Process(parent.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            descendants = []
        if ready(descendants):
            return descendants
        time.sleep(0.5)
    os.kill(parent.pid, signal.SIGKILL)
    pytest.fail(f"not ready within {timeout_s} s")


def _cmdline(p: psutil.Process) -> str:
    try:
        return " ".join(p.cmdline())
    except psutil.Error:
        return ""


def _watching(p: psutil.Process) -> bool:
    """Whether `p` runs wc.worker_pool's watcher thread (a worker past its start-up, which spawn spends importing
    the stage's modules: a worker orphaned then exits once it gets there)."""
    try:
        return any(Path(f"/proc/{p.pid}/task/{t.id}/comm").read_text().strip() == WATCHER_NAME for t in p.threads())
    except (OSError, psutil.Error):
        return False


def _simulate(tmp_path: Path, *overrides: str) -> subprocess.Popen:
    """`python -m stages.simulate` on two short tasks, writing under `tmp_path`."""
    args = ["--set", "agent.tasks=[bag_drop, lift_handle]", "--set", "agent.max_attempts_per_task=1",
            *[a for o in overrides for a in ("--set", o)], "--out", str(tmp_path / "raw.zarr"),
            "--report", str(tmp_path / "simulate.json"), "--memory", ""]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    return subprocess.Popen([sys.executable, "-m", "stages.simulate", *args], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def test_the_watcher_thread_alone_ends_an_orphaned_worker():
    """The portable half: a child that only runs watch_parent (no parent-death signal) exits once its parent is
    killed; a child of the same parent that does not watch is left running."""
    child = ("import os, sys, time\n"
             "if sys.argv[1] == 'watch':\n"
             "    from wc.worker_pool import watch_parent\n"
             "    watch_parent(os.getppid())\n"
             "print('ready', flush=True)\n"
             "time.sleep(600)\n")
    parent = subprocess.Popen(_python(
        "import subprocess, sys, time\n"
        f"kids = [subprocess.Popen([sys.executable, '-c', {child!r}, mode], stdout=subprocess.PIPE, text=True)\n"
        "        for mode in ('watch', 'ignore')]\n"
        "for kid in kids:\n"
        "    kid.stdout.readline()\n"
        "print(' '.join(str(kid.pid) for kid in kids), flush=True)\n"
        "time.sleep(600)\n"), cwd=ROOT, stdout=subprocess.PIPE, text=True)
    watching, ignoring = (psutil.Process(int(pid)) for pid in parent.stdout.readline().split())
    try:
        alive = _kill_and_wait(parent, [watching])
        assert alive == [] and _alive([ignoring]) != []  # the bare child shows what happens without the watch
    finally:
        ignoring.kill()


def test_the_reaper_kills_the_descendants_of_a_killed_process():
    """A child and a grandchild started inside reaping_descendants() are killed when their ancestor is killed -9."""
    parent = subprocess.Popen(_python(
        "import subprocess, sys, time\n"
        "from wc.reaper import reaping_descendants\n"
        "with reaping_descendants():\n"
        "    child = subprocess.Popen([sys.executable, '-c', 'import subprocess, sys, time; "
        "subprocess.Popen([sys.executable, \"-c\", \"import time; time.sleep(600)\"]); time.sleep(600)'])\n"
        "    print('started', flush=True)\n"
        "    time.sleep(600)\n"), cwd=ROOT, stdout=subprocess.PIPE, text=True)
    parent.stdout.readline()
    tree = _wait_for(parent, lambda d: sum("sleep(600)" in _cmdline(p) for p in d) == 2, 60)
    assert _kill_and_wait(parent, tree) == []  # the sleepers and the reaper, once it has killed them


def test_the_reaper_kills_a_process_orphaned_before_it_looked():
    """A grandchild whose parent exits at once (a daemon's double start) is re-parented to init before the watcher's
    next look; it still dies with the block's process, found by the token it inherited."""
    parent = subprocess.Popen(_python(
        "import subprocess, sys, time\n"
        "from wc.reaper import reaping_descendants\n"
        "with reaping_descendants():\n"
        "    child = subprocess.run([sys.executable, '-c', 'import subprocess, sys; "
        "print(subprocess.Popen([sys.executable, \"-c\", \"import time; time.sleep(600)\"], "
        "stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).pid)'], "
        "capture_output=True, text=True)\n"
        "    print(child.stdout.strip(), flush=True)\n"
        "    time.sleep(600)\n"), cwd=ROOT, stdout=subprocess.PIPE, text=True)
    orphan = psutil.Process(int(parent.stdout.readline()))
    assert orphan.ppid() != parent.pid  # not the block's descendant any more
    assert _kill_and_wait(parent, [orphan]) == []


@pytest.mark.slow
def test_simulate_agent_workers_end_with_a_killed_stage(tmp_path):
    """simulate with 2 agent worker processes, killed -9 while they work: no worker outlives it."""
    stage = _simulate(tmp_path, "agent.workers=2")

    def working(descendants: list[psutil.Process]) -> bool:
        workers = [p for p in descendants if "spawn_main" in _cmdline(p)]
        return len(workers) == 2 and all(_watching(p) for p in workers)  # started up: bound to the stage

    descendants = _wait_for(stage, working, 600)
    assert _kill_and_wait(stage, descendants) == []


@pytest.mark.slow
def test_simulate_on_a_local_ray_instance_ends_with_a_killed_stage(tmp_path):
    """simulate on the ray executor without an address starts a Ray instance here; killed -9 once a Ray worker
    runs a unit, none of the instance's processes (GCS, raylet, agents, workers) outlives it."""
    stage = _simulate(tmp_path, "agent.executor=ray", "agent.workers=1")
    descendants = _wait_for(stage, lambda d: any("ray::run_unit" in _cmdline(p) for p in d), 600)
    assert _kill_and_wait(stage, descendants) == []
