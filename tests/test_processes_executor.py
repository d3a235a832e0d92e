"""The processes executor (wc.distributed.processes): one spawned process per device, pinned to its GPU before
anything in it initialises CUDA; results filed in proposal order; a unit that raises stops the stage with an error
naming it; its params errors name the key; and the simulate stage writes the same store on it as on `local`."""

from __future__ import annotations

import json

import pytest

from tests.conftest import load_params
from tests.flaky_units import flaky_doubler
from tests.pinned_units import pinned_view
from tests.test_distributed import Fixed
from tests.test_ray_stages import _same_stores
from tests.test_simulate_workers import TWO_TASKS
from wc.agent.runner import AgentConfig
from wc.agent.simulate_stage import simulate
from wc.config import ParamsError, load_section
from wc.distributed import ProcessesConfig, WorkerSpec, drive, open_executor
from wc.distributed.processes import DEFAULT_CPU_PROCESSES, ProcessesExecutor, UnitError, placement


@pytest.mark.parametrize("devices, gpus, expected", [
    (0, ["0", "1"], ["0", "1"]),
    (3, ["0", "1"], ["0", "1", "0"]),
    (1, ["5", "7"], ["5"]),
    (0, [], [None] * DEFAULT_CPU_PROCESSES),
    (3, [], [None, None, None]),
])
def test_placement_pins_process_k_to_gpu_k(devices, gpus, expected):
    assert placement(ProcessesConfig(devices), gpus) == expected


@pytest.mark.parametrize("key, value, message", [
    ("processes.devices", -1, r"processes: devices must be >= 0 \(0: one process per visible GPU\), got -1"),
    ("processes.devices", 1.5, "processes.devices must be an integer, got 1.5"),
    ("agent.executor", "procs", "agent: executor must be local, ray or processes, got 'procs'"),
])
def test_bad_processes_params_are_named(key, value, message):
    section = key.split(".")[0]
    with pytest.raises(ParamsError, match=message):
        load_section(load_params(f"{key}={value}"), section, {"agent": AgentConfig}.get(section, ProcessesConfig))


@pytest.mark.slow  # spawned processes import the stages' modules
def test_units_are_filed_in_proposal_order_and_spread_over_the_processes(tmp_path):
    streams = [Fixed(WorkerSpec("double", flaky_doubler, (str(tmp_path), "always", -1)), 5) for _ in range(2)]
    with open_executor("processes", load_params("processes.devices=2"), gpu=False) as executor:
        assert list(drive(executor, streams, 3)) == [0, 1]
    assert [s.filed for s in streams] == [[0, 2, 4, 6, 8]] * 2
    report = executor.report()
    assert report["devices"] == ["cpu", "cpu"] and report["units"] == 10 and sum(report["units_per_process"]) == 10


@pytest.mark.slow  # spawned processes import the stages' modules
def test_a_unit_that_raises_stops_the_stage_naming_it(tmp_path):
    stream = Fixed(WorkerSpec("fails", flaky_doubler, (str(tmp_path), "always", 1)), 4)
    with pytest.raises(UnitError, match=r"unit 1 failed in device process \d \(cpu\): RuntimeError: injected failure"):
        with ProcessesExecutor([None, None]) as executor:
            list(drive(executor, [stream], 2))
    assert stream.filed in ([], [0])  # unit 0 is filed only if it finished before unit 1 failed


@pytest.mark.slow  # spawned processes import the stages' modules
def test_a_unit_whose_process_dies_stops_the_stage_naming_it(tmp_path):
    stream = Fixed(WorkerSpec("dies", flaky_doubler, (str(tmp_path), "die_once", 2)), 4)
    with pytest.raises(UnitError, match=r"unit 2 failed in device process \d \(cpu\)"):
        with ProcessesExecutor([None]) as executor:
            list(drive(executor, [stream], 2))


@pytest.mark.slow
def test_each_process_is_pinned_before_cuda_is_initialised():
    streams = [Fixed(WorkerSpec("pinned", pinned_view, ("x",)), 2)]
    with ProcessesExecutor(["3", "5"]) as executor:
        list(drive(executor, streams, 2))
    views = streams[0].filed
    assert {(gpu, initialised) for gpu, initialised, _ in views} <= {("3", False), ("5", False)}
    assert len({pid for _, _, pid in views}) == 2  # both units in flight at once: one per process


@pytest.mark.slow
def test_simulate_writes_the_same_store_and_memory_in_device_processes(tmp_path):
    runs = {}
    for executor in ("local", "processes"):
        params = load_params(*TWO_TASKS, "agent.episodes_per_task=2", "agent.max_attempts_per_task=3",
                             "agent.workers=1", f"agent.executor={executor}", "agent.batches_in_flight=2",
                             "processes.devices=2")
        d = tmp_path / executor
        runs[executor] = d, simulate(params, d / "raw.zarr", d / "simulate.json", d / "memory.json")
    (local, a), (processes, b) = runs["local"], runs["processes"]
    assert len(_same_stores(local / "raw.zarr", processes / "raw.zarr")) >= 4
    memories = [json.loads((d / "memory.json").read_text())["outcomes"] for d in (local, processes)]
    assert memories[0] == memories[1]
    assert a["params_hash"] == b["params_hash"] and a["accepted"] == b["accepted"]
    for name, task in a["tasks"].items():
        assert {**task, "wall_s": 0} == {**b["tasks"][name], "wall_s": 0}, name
    assert b["executor"]["devices"] == ["cpu", "cpu"] and b["executor"]["units"] == b["episodes"]
    assert min(b["executor"]["units_per_process"]) > 0  # two batches in flight: both processes simulated
