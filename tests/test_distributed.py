"""The executors of the data stages (wc.distributed): the executor params and their errors, streams filing results
in proposal order whatever order units finish in, and the ray executor's retries of a unit that raised or whose
worker died, and its record of a unit that kept failing."""

from __future__ import annotations

import logging
import random
from collections.abc import Hashable
from typing import Any

import pytest

from tests.conftest import ROOT, load_params
from tests.flaky_units import flaky_doubler
from wc.agent.runner import AgentConfig
from wc.config import ParamsError, load_section, read_params
from wc.distributed import LocalExecutor, RayConfig, RayExecutor, Unit, WorkerSpec, drive, open_executor
from wc.expand.config import ExpandConfig
from wc.render.config import RenderConfig

SECTIONS = {"agent": AgentConfig, "expand": ExpandConfig, "render": RenderConfig}


@pytest.mark.parametrize("section", sorted(SECTIONS))
@pytest.mark.parametrize("value", ["dask", "Ray", ""])
def test_a_bad_executor_is_named(section, value):
    with pytest.raises(ParamsError, match=rf"{section}: executor must be local, ray or processes, got '{value}'"):
        load_section(load_params(f"{section}.executor='{value}'"), section, SECTIONS[section])


@pytest.mark.parametrize("key, value, message", [
    ("agent.batches_in_flight", 0, "agent: batches_in_flight must be >= 1, got 0"),
    ("agent.memory", "old", "agent: memory must be fresh or kept, got 'old'"),
    ("expand.batches_in_flight", -1, "expand: batches_in_flight must be >= 1, got -1"),
    ("render.episodes_per_unit", 0, "render: episodes_per_unit must be a positive integer, got 0"),
    ("ray.address", "' '", "ray: address must be null or a Ray address .*, got ' '"),
    ("ray.max_retries", -1, "ray: max_retries must be >= 0, got -1"),
    ("ray.cpus_per_unit", 0, "ray: cpus_per_unit must be positive, got 0"),
    ("ray.gpus_per_unit", 1.5, r"ray: gpus_per_unit must be a fraction in \(0, 1\] or a whole number of GPUs, got 1.5"),
    ("ray.gpus_per_unit", 0, "ray: gpus_per_unit must be a fraction"),
    ("ray.max_retries", 1.5, "ray.max_retries must be an integer, got 1.5"),
])
def test_bad_ray_params_are_named(key, value, message):
    section = key.split(".")[0]
    with pytest.raises(ParamsError, match=message):
        load_section(load_params(f"{key}={value}"), section, SECTIONS.get(section, RayConfig))


@pytest.mark.parametrize("file", ["params.yaml", "params/gpu.yaml"])
def test_shipped_params_run_locally_by_default(file):
    params = read_params(ROOT / file)
    assert {load_section(params, s, c).executor for s, c in SECTIONS.items()} == {"local"}
    assert load_section(params, "ray", RayConfig) == RayConfig()


def test_a_ray_section_with_an_unknown_key_fails_before_ray_starts(tmp_path):
    params = load_params()
    params["ray"]["nodes"] = 4
    with pytest.raises(ParamsError, match="unknown key ray.nodes"):
        with open_executor("ray", params, gpu=False):
            pass


class Planned:
    """A stream whose next payload depends on every result filed before it (as a planner's proposals do)."""

    def __init__(self, worker: WorkerSpec, units: int) -> None:
        self.worker, self.units = worker, units
        self.proposed: list[int] = []
        self.filed: list[int] = []

    def next_unit(self) -> Unit | None:
        if len(self.proposed) == self.units:
            return None
        payload = sum(self.filed) % 7 + len(self.proposed)
        self.proposed.append(payload)
        return Unit(self.worker, payload, f"unit {payload}")

    def file(self, result: int) -> None:
        self.filed.append(result)


class Shuffled(LocalExecutor):
    """Runs each unit when submitted and hands the finished ones back in random order, several at a time."""

    def __init__(self, seed: int) -> None:
        super().__init__()
        self.rng, self.finished = random.Random(seed), {}

    def submit(self, unit: Unit) -> int:
        ticket = super().submit(unit)
        self.finished.update(super().wait())
        return ticket

    def wait(self) -> dict[Hashable, Any]:
        tickets = self.rng.sample(sorted(self.finished), self.rng.randint(1, len(self.finished)))
        return {t: self.finished.pop(t) for t in tickets}


def _doubler() -> WorkerSpec:
    return WorkerSpec("double", lambda: lambda x: 2 * x)


@pytest.mark.parametrize("in_flight", [1, 3])
def test_streams_file_in_proposal_order_whatever_order_units_finish(in_flight):
    local = [Planned(_doubler(), 9), Planned(_doubler(), 4)]
    assert list(drive(LocalExecutor(), local, in_flight)) == [0, 1]
    for seed in range(5):
        shuffled = [Planned(_doubler(), 9), Planned(_doubler(), 4)]
        assert list(drive(Shuffled(seed), shuffled, in_flight)) == [0, 1]
        for a, b in zip(local, shuffled):
            assert (a.proposed, a.filed) == (b.proposed, b.filed)
            assert a.filed == [2 * p for p in a.proposed]


def test_the_local_executor_raises_at_once():
    stream = Planned(WorkerSpec("fails", lambda: lambda x: 1 / 0), 3)
    with pytest.raises(ZeroDivisionError):
        list(drive(LocalExecutor(), [stream], 2))
    assert stream.filed == []


class Fixed(Planned):
    """Payloads 0, 1, 2, ... whatever was filed."""

    def next_unit(self) -> Unit | None:
        if len(self.proposed) == self.units:
            return None
        self.proposed.append(len(self.proposed))
        return Unit(self.worker, self.proposed[-1], f"unit {self.proposed[-1]}")


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raise_once", "die_once"])
def test_a_unit_whose_worker_raised_or_died_is_retried(local_ray, tmp_path, mode):
    executor = RayExecutor(RayConfig(max_retries=1), gpu=False, address="test")
    stream = Fixed(WorkerSpec(f"flaky-{mode}", flaky_doubler, (str(tmp_path), mode, 2)), 4)
    assert list(drive(executor, [stream], 2)) == [0]
    assert stream.filed == [0, 2, 4, 6] and executor.failures == []
    assert (tmp_path / f"{mode}-2").read_text() == "x"  # it failed once, then ran again


@pytest.mark.slow
def test_a_unit_that_keeps_failing_is_logged_counted_and_ends_its_stream(local_ray, tmp_path, caplog):
    executor = RayExecutor(RayConfig(max_retries=2), gpu=False, address="test")
    failing = Fixed(WorkerSpec("flaky-always", flaky_doubler, (str(tmp_path), "always", 1)), 6)
    other = Fixed(WorkerSpec("double", flaky_doubler, (str(tmp_path), "always", -1)), 6)
    with caplog.at_level(logging.ERROR, logger="wc.distributed.executors"):
        assert list(drive(executor, [failing, other], 2)) == [0, 1]
    assert failing.filed == [0]  # nothing after the failed unit is filed
    assert (tmp_path / "always-1").read_text() == "xxx"  # 1 + max_retries tries
    assert other.filed == [2 * p for p in other.proposed[:len(other.filed)]]  # the other stream's, in order
    report = executor.report()
    assert report["units"] == len(failing.proposed) + len(other.proposed)
    assert report["failed_units"] == [{"label": "unit 1", "error": "RuntimeError: injected failure on unit 1"}]
    assert "unit 1 kept failing (3 tries): RuntimeError: injected failure on unit 1" in caplog.text


@pytest.mark.slow
def test_a_stage_uses_the_ray_this_process_started(local_ray):
    import ray

    with open_executor("ray", load_params(), gpu=True) as executor:
        assert executor.address == "this process's Ray" and executor.resources == {"num_cpus": 1.0, "num_gpus": 1.0}
    assert ray.is_initialized()


def test_the_gpu_benchmark_asks_for_valid_params():
    """A wrong key in benchmarks/simulate_ray.py would cost a GPU call."""
    import argparse

    from benchmarks import simulate_ray as bench

    args = argparse.Namespace(params=ROOT / "params.yaml", device="cuda", worlds=8, task="lift_handle", overrides=[])
    params = bench.bench_params(args, "ray", 8)
    agent, ray = load_section(params, "agent", AgentConfig), load_section(params, "ray", RayConfig)
    assert (agent.executor, agent.batches_in_flight, agent.tasks) == ("ray", 8, ("lift_handle",))
    assert ray.gpus_per_unit == 0.125
