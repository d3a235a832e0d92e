"""A reaper for the processes a stage starts through a library it cannot make end with it.

A local Ray instance (`ray.init()` without an address) starts its GCS server and raylet bound to the driver (Ray's
kernel fate-sharing), but the raylet's children, Ray's agents and its worker processes, are re-parented to init when
a killed driver takes the raylet with it, and some of them ran on for a minute or more. `reaping_descendants()`
starts a small watcher process that follows this process's descendants; when this process ends without closing the
block (SIGKILL included), the watcher kills every descendant it last saw and every process that carries the block's
token in its environment (inherited by whatever starts inside the block, so a process started and orphaned between
two looks, or before the watcher's first one, is found too).

    python -m wc.reaper PID TOKEN     # the watcher: PID must be its parent
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import psutil

POLL_S = 0.2  # how often the watcher looks at the tree
QUIET_LOOKS = 3  # after the parent died: tagged processes are looked for until this many looks in a row find none
TOKEN_VAR = "WC_REAPER_TOKEN"  # the environment variable that marks the processes started inside the block
READY = "watching"  # what the watcher prints once it has looked at the tree


def tagged_processes(token: str) -> list[psutil.Process]:
    """The processes (other than this one) whose environment carries `token` under TOKEN_VAR."""
    me, found = os.getpid(), []
    for process in psutil.process_iter():
        try:
            if process.pid != me and process.environ().get(TOKEN_VAR) == token:
                found.append(process)
        except psutil.Error:  # gone, a zombie, or another user's
            pass
    return found


def _kill(processes: list[psutil.Process]) -> list[int]:
    killed = []
    for process in processes:
        try:
            process.kill()  # psutil refuses a pid that another process has taken since
            killed.append(process.pid)
        except psutil.Error:  # gone since, or not ours to kill: the rest still die
            pass
    return killed


def reap_when_parent_dies(parent_pid: int, token: str, poll_s: float = POLL_S) -> list[int]:
    """Follow `parent_pid`'s descendants (other than this process) until this process's parent is no longer
    `parent_pid`, then kill those last seen and every process tagged with `token`; returns the pids killed."""
    me = os.getpid()
    seen: list[psutil.Process] = []
    ready = False
    try:
        parent = psutil.Process(parent_pid)
        while os.getppid() == parent_pid:
            seen = [p for p in parent.children(recursive=True) if p.pid != me]
            if not ready:
                print(READY, flush=True)
                ready = True
            time.sleep(poll_s)
    except psutil.NoSuchProcess:
        pass
    killed = _kill(seen)
    quiet = 0
    for _ in range(QUIET_LOOKS * 10):  # a tagged process may be starting another: look until a few looks find none
        more = _kill(tagged_processes(token))
        killed += more
        quiet = 0 if more else quiet + 1
        if quiet == QUIET_LOOKS:
            break
        time.sleep(poll_s)
    return list(dict.fromkeys(killed))


@contextmanager
def reaping_descendants() -> Iterator[None]:
    """Within the block, this process's descendants die with it even if it is killed; a normal exit from the block
    stops the watcher (it kills nothing). The block starts once the watcher is watching."""
    token = uuid.uuid4().hex
    watcher = subprocess.Popen([sys.executable, "-m", "wc.reaper", str(os.getpid()), token],
                               stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True,
                               cwd=Path(__file__).resolve().parents[1],  # where `wc` imports from
                               start_new_session=True)  # a Ctrl-C to the stage's process group leaves it watching
    before = os.environ.get(TOKEN_VAR)
    try:
        if watcher.stdout.readline().strip() != READY:
            raise RuntimeError(f"the reaper's watcher did not start (status {watcher.poll()})")
        os.environ[TOKEN_VAR] = token
        yield
    finally:
        if before is None:
            os.environ.pop(TOKEN_VAR, None)
        else:
            os.environ[TOKEN_VAR] = before
        watcher.terminate()
        watcher.wait()
        watcher.stdout.close()


if __name__ == "__main__":
    reap_when_parent_dies(int(sys.argv[1]), sys.argv[2])
