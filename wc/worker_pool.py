"""Process pools whose workers end with the process that started them.

A stage killed with SIGKILL runs no clean-up, so the worker processes of its pool would be re-parented to init and
run on, holding memory and the device. Every worker of `spawn_pool` ends with its parent in two ways: on Linux the
kernel sends it SIGKILL when its parent dies (prctl PR_SET_PDEATHSIG), and on any platform a daemon thread in the
worker polls the parent's pid and exits the worker once the parent is gone. Workers start with `spawn`: warp, Newton
and CUDA must not be forked once initialised.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_POLL_S = 0.5  # how often the watcher thread looks for the parent


def _kill_on_parent_death() -> bool:
    """Ask the Linux kernel to SIGKILL this process when the thread that started it ends; False where unsupported.
    The pools are made in a stage's main thread, so that thread ends with the stage."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent_pid: int) -> None:
    """Exit this process once its parent is gone (its parent pid changes to the reaper's)."""
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


def end_with_parent(parent_pid: int) -> None:
    """Make this process end when `parent_pid` (its parent) ends: a parent-death signal where the kernel has one,
    and a watcher thread everywhere. A parent already gone ends this process now."""
    _kill_on_parent_death()
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name="watch-parent", daemon=True).start()


def _start_worker(parent_pid: int, initializer: Callable[..., None] | None, initargs: tuple[Any, ...]) -> None:
    end_with_parent(parent_pid)
    if initializer is not None:
        initializer(*initargs)


def spawn_pool(workers: int, initializer: Callable[..., None] | None = None,
               initargs: tuple[Any, ...] = ()) -> ProcessPoolExecutor:
    """A pool of `workers` spawned processes, each running `initializer(*initargs)` at start-up (a module-level
    function: it is pickled) and ending with this process, however this process ends."""
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                               initargs=(os.getpid(), initializer, initargs))
