"""A reaper for the processes a stage starts through a library it cannot make end with it.

A local Ray instance (`ray.init()` without an address) starts its GCS server and raylet bound to the driver (Ray's
kernel fate-sharing), but the raylet's children, Ray's agents and its worker processes, are re-parented to init when
a killed driver takes the raylet with it, and some of them ran on for a minute or more. `reaping_descendants()`
starts a small watcher process that follows this process's descendants; when this process ends without closing the
block (SIGKILL included), the watcher kills every descendant it last saw.

    python -m wc.reaper PID     # the watcher: PID must be its parent
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import psutil

POLL_S = 0.2  # how often the watcher looks at the tree (a process started and orphaned within it is missed)


def reap_when_parent_dies(parent_pid: int, poll_s: float = POLL_S) -> list[int]:
    """Follow `parent_pid`'s descendants (other than this process) until this process's parent is no longer
    `parent_pid`, then kill those last seen that still run; returns the pids killed."""
    me = os.getpid()
    try:
        parent = psutil.Process(parent_pid)
    except psutil.NoSuchProcess:
        return []
    seen: list[psutil.Process] = []
    while os.getppid() == parent_pid:
        try:
            seen = [p for p in parent.children(recursive=True) if p.pid != me]
        except psutil.NoSuchProcess:
            break
        time.sleep(poll_s)
    killed = []
    for process in seen:
        try:
            process.kill()  # psutil refuses a pid that another process has taken since
            killed.append(process.pid)
        except psutil.NoSuchProcess:
            pass
    return killed


@contextmanager
def reaping_descendants() -> Iterator[None]:
    """Within the block, this process's descendants die with it even if it is killed; a normal exit from the block
    stops the watcher (it kills nothing)."""
    watcher = subprocess.Popen([sys.executable, "-m", "wc.reaper", str(os.getpid())], stdin=subprocess.DEVNULL,
                               cwd=Path(__file__).resolve().parents[1],  # where `wc` imports from
                               start_new_session=True)  # a Ctrl-C to the stage's process group leaves it watching
    try:
        yield
    finally:
        watcher.terminate()
        watcher.wait()


if __name__ == "__main__":
    reap_when_parent_dies(int(sys.argv[1]))
