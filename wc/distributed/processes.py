"""The `processes` executor: one spawned worker process per device of this host, each pinned to its GPU.

Process k sees only its GPU (CUDA_VISIBLE_DEVICES, set in the process before anything in it initialises CUDA:
importing wc, torch, warp or Newton does not), so a unit's `cuda` device is that GPU; on a host without GPUs the
processes are plain CPU processes. A unit goes to an idle process, which runs one unit at a time and keeps its workers
between units (`run_unit`, with the driver's torch thread count), so a unit's result does not depend on which process
ran it. A unit that raises, or whose process dies, ends the stage with an error naming the unit, as the local
executor's does (no retry). The processes end with the stage however it ends (wc.worker_pool).
"""

from __future__ import annotations

import os
import sys
from collections import deque
from collections.abc import Collection, Hashable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any

import torch

from wc.distributed.config import ProcessesConfig
from wc.distributed.executors import Unit, UnitFailure, run_unit
from wc.worker_pool import spawn_pool

DEFAULT_CPU_PROCESSES = 2  # `processes.devices: 0` on a host without GPUs


def visible_gpus() -> list[str]:
    """The GPUs this process may use, as CUDA_VISIBLE_DEVICES entries (its own list where that is set)."""
    count = torch.cuda.device_count()  # counts without creating a CUDA context
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    if listed is None:
        return [str(i) for i in range(count)]
    return [d.strip() for d in listed.split(",") if d.strip()][:count]


def placement(cfg: ProcessesConfig, gpus: list[str] | None = None) -> list[str | None]:
    """The GPU each device process is pinned to (None: a CPU process): `cfg.devices` processes, process k on GPU
    k mod the GPU count; devices 0: one per GPU, or DEFAULT_CPU_PROCESSES CPU processes where there is none."""
    gpus = visible_gpus() if gpus is None else gpus
    if not gpus:
        return [None] * (cfg.devices or DEFAULT_CPU_PROCESSES)
    return [gpus[k % len(gpus)] for k in range(cfg.devices or len(gpus))]


def cuda_initialised() -> bool:
    """Whether torch or warp has initialised CUDA in this process (after which CUDA_VISIBLE_DEVICES is not read)."""
    warp_context = sys.modules.get("warp._src.context")
    return torch.cuda.is_initialized() or getattr(warp_context, "runtime", None) is not None


def pin_to_gpu(gpu: str | None) -> None:
    """A device process's start-up: make `gpu` its only visible GPU (None: leave a CPU process as it is)."""
    if gpu is None:
        return
    if cuda_initialised():
        raise RuntimeError(f"processes executor: CUDA was initialised before this process could be pinned to GPU {gpu}")
    os.environ["CUDA_VISIBLE_DEVICES"] = gpu


def _end_now(pool: ProcessPoolExecutor) -> None:
    """Stop `pool` without waiting for the unit it runs (a failed stage ends now, not after its slowest unit)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())  # no terminate_workers before Python 3.14
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()


class UnitError(RuntimeError):
    """A unit raised in a device process (or its process died): the stage stops."""


class ProcessesExecutor:
    """Units in one spawned process per entry of `gpus` (module docstring); `wait` returns whichever finish first.
    Use as a context manager: the processes end on exit."""

    name = "processes"
    stopping = False  # a failing unit raises: there is never a failed unit to stop for

    def __init__(self, gpus: list[str | None]) -> None:
        if not gpus:
            raise ValueError("processes executor: no device processes to start")
        self.gpus = gpus
        self._pools = [spawn_pool(1, pin_to_gpu, (gpu,)) for gpu in gpus]
        self._idle: deque[int] = deque(range(len(gpus)))
        self._queue: deque[tuple[int, Unit]] = deque()
        self._running: dict[Future[Any], tuple[int, int, str]] = {}  # -> (ticket, process, unit label)
        self._cancelled: set[int] = set()
        self._threads = torch.get_num_threads()  # the same in every process, whatever the placement
        self.units = 0
        self.units_per_process = [0] * len(gpus)
        self.failures: list[UnitFailure] = []  # always empty

    def device(self, process: int) -> str:
        gpu = self.gpus[process]
        return "cpu" if gpu is None else f"gpu {gpu}"

    def submit(self, unit: Unit) -> int:
        self.units += 1
        self._queue.append((self.units, unit))
        self._dispatch()
        return self.units

    def _dispatch(self) -> None:
        while self._idle and self._queue:
            ticket, unit = self._queue.popleft()
            process = self._idle.popleft()
            future = self._pools[process].submit(run_unit, unit.worker, unit.payload, self._threads)
            self._running[future] = (ticket, process, unit.label)
            self.units_per_process[process] += 1

    def wait(self) -> dict[Hashable, Any]:
        """{ticket: result} of the units that finished first (at least one); UnitError if one of them raised."""
        out: dict[Hashable, Any] = {}
        while not out:
            done, _ = wait(self._running, return_when=FIRST_COMPLETED)
            for future in sorted(done, key=lambda f: self._running[f][0]):  # the first failing unit in ticket order
                ticket, process, label = self._running.pop(future)
                self._idle.append(process)
                if ticket in self._cancelled:
                    self._cancelled.discard(ticket)
                    continue
                try:
                    out[ticket] = future.result()
                except Exception as err:
                    text = " ".join(f"{type(err).__name__}: {err}".split())[:400]
                    raise UnitError(f"processes executor: {label} failed in device process {process} "
                                    f"({self.device(process)}): {text}") from err
            self._dispatch()
        return out

    def cancel(self, tickets: Collection[Hashable]) -> None:
        self._queue = deque(item for item in self._queue if item[0] not in tickets)
        self._cancelled.update(t for t, _, _ in self._running.values() if t in tickets)

    def report(self) -> dict[str, Any]:
        return {"name": self.name, "devices": [self.device(k) for k in range(len(self.gpus))], "units": self.units,
                "units_per_process": self.units_per_process}

    def __enter__(self) -> ProcessesExecutor:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc: object) -> None:
        for pool in self._pools:
            if kind is None and not self._running:
                pool.shutdown(wait=True)
            else:
                _end_now(pool)
