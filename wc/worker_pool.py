"""Process pools whose workers end with the process that started them.

A stage killed with SIGKILL runs no clean-up, so the worker processes of its pool would be re-parented to init and
run on, holding memory and the device. Every worker of `spawn_pool` ends with its parent in two ways: on Linux the
kernel sends it SIGKILL when its parent dies (prctl PR_SET_PDEATHSIG), and on any platform a daemon thread in the
worker polls the parent's pid and exits the worker once the parent is gone. Workers start with `spawn`: warp, Newton
and CUDA must not be forked once initialised. The initializer's arguments reach the workers through a file: written to
a spawned child's pipe, more than a pipe's buffer (64 KiB) would hold the parent until that child had imported its
modules, one worker after another, before the parent could go on (~5 s a worker).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import pickle
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

PR_SET_PDEATHSIG, PR_SET_NAME = 1, 15  # linux/prctl.h
PARENT_POLL_S = 0.5  # how often the watcher thread looks for the parent
WATCHER_NAME = "watch-parent"  # the watcher thread's name, also its OS name on Linux (`ps -L`, /proc/PID/task/*/comm)


def _prctl(option: int, arg: int | bytes) -> bool:
    """Linux prctl(option, arg); False where there is none or it fails."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True).prctl(option, arg, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _kill_on_parent_death() -> bool:
    """Ask the Linux kernel to SIGKILL this process when the thread that started it ends; False where unsupported.
    The pools are made in a stage's main thread, so that thread ends with the stage."""
    return _prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def _exit_when_orphaned(parent_pid: int) -> None:
    _prctl(PR_SET_NAME, WATCHER_NAME.encode())  # names this thread: a worker that watches can be told from outside
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


def watch_parent(parent_pid: int) -> threading.Thread:
    """Start (and return) a daemon thread that exits this process once its parent pid is no longer `parent_pid`
    (the parent died and init, or a subreaper, adopted it): the portable half of `end_with_parent`."""
    thread = threading.Thread(target=_exit_when_orphaned, args=(parent_pid,), name=WATCHER_NAME, daemon=True)
    thread.start()
    return thread


def end_with_parent(parent_pid: int) -> None:
    """Make this process end when `parent_pid` (its parent) ends: a parent-death signal where the kernel has one,
    and a watcher thread everywhere. A parent already gone ends this process now."""
    _kill_on_parent_death()
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)
    watch_parent(parent_pid)


def _start_worker(parent_pid: int, initializer: Callable[..., None] | None, initargs_file: str) -> None:
    end_with_parent(parent_pid)  # a parent killed while this worker imported the stage's modules: exit now
    if initializer is not None:
        try:
            with open(initargs_file, "rb") as f:
                initargs = pickle.load(f)
        except FileNotFoundError:  # the pool was shut down before this worker started
            os._exit(0)
        initializer(*initargs)


class _SpawnPool(ProcessPoolExecutor):
    """A process pool that removes its initializer's argument file once shut down."""

    def __init__(self, workers: int, initializer: Callable[..., None] | None, initargs: tuple[Any, ...]) -> None:
        with tempfile.NamedTemporaryFile("wb", prefix="wc-pool-", suffix=".pkl", delete=False) as f:
            pickle.dump(initargs, f, protocol=pickle.HIGHEST_PROTOCOL)
        self.initargs_file = f.name
        super().__init__(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                         initargs=(os.getpid(), initializer, f.name))

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        super().shutdown(wait=wait, cancel_futures=cancel_futures)
        try:
            os.remove(self.initargs_file)
        except FileNotFoundError:
            pass


def cores_each(workers: int) -> int:
    """This machine's cores shared out between `workers` processes, at least one each: torch threads per worker
    (more, and the workers' OpenMP threads spin against each other)."""
    return max(1, (os.cpu_count() or 1) // workers)


def spawn_pool(workers: int, initializer: Callable[..., None] | None = None,
               initargs: tuple[Any, ...] = ()) -> ProcessPoolExecutor:
    """A pool of `workers` spawned processes, each running `initializer(*initargs)` at start-up (a module-level
    function: it is pickled; initargs travel pickled through a temporary file) and ending with this process, however
    this process ends."""
    return _SpawnPool(workers, initializer, initargs)
