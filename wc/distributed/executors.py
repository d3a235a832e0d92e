"""Where a data stage's work units run.

A unit is a pure call: a worker, built once per process from a picklable `WorkerSpec` and kept for later units of
the same spec, applied to a payload; its result depends on the spec and the payload alone, so it is the same
wherever and whenever the unit runs. `LocalExecutor` runs each unit in this process when its result is wanted, in
the order the units were submitted (what the stages did before executors); `RayExecutor` runs them as Ray tasks
that ask for the CPUs or GPUs they need, retried (Ray's max_retries) when their worker raised or died, and logged
and recorded as failed when they kept failing; `ProcessesExecutor` (wc.distributed.processes) runs them in one
spawned process per GPU of this host. `open_executor` picks one by a stage's `executor` value.
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict, deque
from collections.abc import Callable, Collection, Hashable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import torch

from wc.config import load_section
from wc.distributed.config import ProcessesConfig, RayConfig, check_executor
from wc.reaper import reaping_descendants

if TYPE_CHECKING:
    from wc.distributed.processes import ProcessesExecutor

log = logging.getLogger(__name__)
KEPT_WORKERS = 2  # workers one Ray worker process keeps (a simulate worker holds a task's Newton world)
FAILED = object()  # the result of a unit that kept failing


@dataclass(frozen=True)
class WorkerSpec:
    """What builds a worker: `build(*args)`, a callable of one payload. Equal keys build interchangeable workers;
    for the Ray executor a spec must pickle (a module-level `build`, picklable `args`)."""

    key: str
    build: Callable[..., Callable[[Any], Any]]
    args: tuple[Any, ...] = ()


@dataclass(frozen=True)
class Unit:
    """One work unit: the worker of `worker` applied to `payload`; `label` names it in logs and reports."""

    worker: WorkerSpec
    payload: Any
    label: str


@dataclass(frozen=True)
class UnitFailure:
    label: str
    error: str  # the last try's exception, on one line


class UnitsFailed(RuntimeError):
    """Work units kept failing on the Ray executor: the stage wrote no store."""

    def __init__(self, stage: str, failures: list[UnitFailure]) -> None:
        listed = "; ".join(f"{f.label}: {f.error}" for f in failures[:3]) + ("; ..." if len(failures) > 3 else "")
        super().__init__(f"{stage}: {len(failures)} work unit(s) kept failing on the ray executor, no store written "
                         f"(the report lists them): {listed}")
        self.failures = failures


class Executor(Protocol):
    """What runs a stage's units (LocalExecutor, RayExecutor, ProcessesExecutor): `submit` returns a ticket, `wait`
    {ticket: result} of units that finished (FAILED for one that kept failing), `stopping` once one did."""

    name: str
    units: int
    failures: list[UnitFailure]

    @property
    def stopping(self) -> bool: ...

    def submit(self, unit: Unit) -> Hashable: ...

    def wait(self) -> dict[Hashable, Any]: ...

    def cancel(self, tickets: Collection[Hashable]) -> None: ...

    def report(self) -> dict[str, Any]: ...


class LocalExecutor:
    """Units run in this process, one at a time in submission order, each when `wait` is called; an exception a
    unit raises propagates (no retry)."""

    name = "local"
    stopping = False  # a failing unit raises: there is never a failed unit to stop for

    def __init__(self) -> None:
        self._workers: dict[str, Callable[[Any], Any]] = {}
        self._queue: deque[tuple[int, Unit]] = deque()
        self.units = 0
        self.failures: list[UnitFailure] = []  # always empty

    def submit(self, unit: Unit) -> int:
        self.units += 1
        self._queue.append((self.units, unit))
        return self.units

    def wait(self) -> dict[Hashable, Any]:
        """The oldest submitted unit, run now: {its ticket: its result}."""
        ticket, unit = self._queue.popleft()
        spec = unit.worker
        if spec.key not in self._workers:
            self._workers[spec.key] = spec.build(*spec.args)
        return {ticket: self._workers[spec.key](unit.payload)}

    def cancel(self, tickets: Collection[Hashable]) -> None:
        self._queue = deque(item for item in self._queue if item[0] not in tickets)

    def report(self) -> dict[str, Any]:
        return {"name": self.name}


_kept: OrderedDict[str, Callable[[Any], Any]] = OrderedDict()  # this worker process's workers, latest last


def run_unit(spec: WorkerSpec, payload: Any, torch_threads: int) -> Any:
    """One unit in a Ray worker or device process, with the driver's torch thread count (as the local pool's
    workers): the worker of `spec` (kept from an earlier unit, else built; dropped if it raises) applied to
    `payload`."""
    torch.set_num_threads(torch_threads)
    worker = _kept.pop(spec.key, None)
    if worker is None:
        worker = spec.build(*spec.args)
    result = worker(payload)  # a worker that raised is not kept: its state may be half-updated
    _kept[spec.key] = worker
    while len(_kept) > KEPT_WORKERS:
        _kept.popitem(last=False)
    return result


class RayExecutor:
    """Units as Ray tasks (`run_unit`) with `cfg`'s resources (GPUs only when `gpu`) and retries; `wait` returns
    whichever finish first. A unit that kept failing is logged, kept in `failures` and returned as FAILED; from
    then on `stopping` is true (the caller starts no new unit)."""

    name = "ray"

    def __init__(self, cfg: RayConfig, gpu: bool, address: str) -> None:
        import ray

        self._ray = ray
        self.cfg, self.address = cfg, address
        self.resources = {"num_cpus": cfg.cpus_per_unit, **({"num_gpus": cfg.gpus_per_unit} if gpu else {})}
        self._task = ray.remote(run_unit).options(max_retries=cfg.max_retries, retry_exceptions=True,
                                                  **self.resources)
        self._threads = torch.get_num_threads()
        self._running: dict[Any, str] = {}  # object ref -> unit label
        self.units = 0
        self.failures: list[UnitFailure] = []

    @property
    def stopping(self) -> bool:
        return bool(self.failures)

    def submit(self, unit: Unit) -> Hashable:
        ref = self._task.remote(unit.worker, unit.payload, self._threads)
        self._running[ref] = unit.label
        self.units += 1
        return ref

    def wait(self) -> dict[Hashable, Any]:
        ready, _ = self._ray.wait(list(self._running), num_returns=1)
        out = {}
        for ref in ready:
            label = self._running.pop(ref)
            try:
                out[ref] = self._ray.get(ref)
            except self._ray.exceptions.RayError as err:
                out[ref] = FAILED
                cause = getattr(err, "cause", None) or err  # RayTaskError.cause: what the unit raised
                text = " ".join(f"{type(cause).__name__}: {cause}".split())[:400]
                self.failures.append(UnitFailure(label, text))
                log.error("ray executor: %s kept failing (%d tries): %s", label, self.cfg.max_retries + 1, text)
        return out

    def cancel(self, tickets: Collection[Hashable]) -> None:
        for ref in tickets:
            if self._running.pop(ref, None) is not None:
                self._ray.cancel(ref)

    def report(self) -> dict[str, Any]:
        return {"name": self.name, "address": self.address, "units": self.units, "resources": self.resources,
                "max_retries": self.cfg.max_retries, "failed_units": [f.__dict__ for f in self.failures]}


@contextmanager
def open_executor(name: str, params: dict[str, Any],
                  gpu: bool) -> Iterator[LocalExecutor | RayExecutor | ProcessesExecutor]:
    """The executor a stage's `executor` value names. ray: the params' `ray` section; connected to ray.address, else
    $RAY_ADDRESS, else a new Ray instance on this machine (shut down on exit, and its processes killed if this
    process is: wc.reaper); a Ray this process already initialised (a test's, a notebook's) is used as it is.
    processes: the params' `processes` section, the processes ended on exit. `gpu`: the units run on a CUDA device
    (ray asks for one; a device process is pinned to its GPU whenever the host has one)."""
    check_executor(name)
    if name == "local":
        yield LocalExecutor()
        return
    if name == "processes":
        from wc.distributed.processes import ProcessesExecutor, placement  # it imports this module

        with ProcessesExecutor(placement(load_section(params, "processes", ProcessesConfig))) as executor:
            yield executor
        return
    cfg = load_section(params, "ray", RayConfig)
    import ray

    address = cfg.address or os.environ.get("RAY_ADDRESS") or None
    started = not ray.is_initialized()
    with reaping_descendants() if started and not address else nullcontext():  # a local instance dies with the stage
        if started:
            ray.init(address=address, **({} if address else {"include_dashboard": False}))
        try:
            yield RayExecutor(cfg, gpu, address or ("a new local Ray instance" if started else "this process's Ray"))
        finally:
            if started:
                ray.shutdown()


@contextmanager
def every_unit(executor: Executor, stage: str) -> Iterator[None]:
    """`with writer, every_unit(executor, stage):` raises UnitsFailed at the end of the block when units kept
    failing, so that the writer, exited after it, discards its store."""
    yield
    if executor.stopping:
        raise UnitsFailed(stage, executor.failures)
