"""World-model training under DistributedDataParallel on CPU processes (gloo): the ranks' gradients are averaged,
a run cut into chunks resumes exactly with every rank's own streams, the ranks share each step's layout, and a
state is resumed only with the process count that saved it."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from tests.conftest import ROOT
from wc.data.store import TrajectoryStore
from wc.train.data import LayoutBatchSampler, phases_of, windows_of
from wc.train.distributed import Processes
from wc.train.loop import rank_streams
from tests.test_train import params, store_path  # noqa: F401  (fixtures: the training tests' tiny store)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train(store_path: Path, out: Path, processes: int, static: bool, steps: int = 2, extra: tuple[str, ...] = (),
           overrides: tuple[str, ...] = (), check: bool = True) -> subprocess.CompletedProcess:
    """The train stage on `processes` CPU processes (gloo; torchrun-style launch when more than one) through
    tests/train_final_weights.py: `steps` steps of the base stage, outputs under `out` (the model in out/m), each
    rank's weights after its last step in out/rank<k>.safetensors."""
    sets = ["train.init_from=''", f"train.static={str(static).lower()}", f"train.base.steps={steps}",
            "train.base.warmup_steps=1", "train.projection.steps=0", "train.projection.warmup_steps=0",
            f"train.eval_every_steps={steps}", "train.val_windows=1", "train.rollout_frames=2", *overrides]
    launch = ([sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(processes), "--master-port",
               str(_free_port())] if processes > 1 else [sys.executable])
    out.mkdir(exist_ok=True)
    cmd = [*launch, "-m", "tests.train_final_weights", str(out), "--store", str(store_path), "--out", str(out / "m"),
           "--report", str(out / "r.json"), "--curves", str(out / "c.csv"), *extra,
           *(a for o in sets for a in ("--set", o))]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    if check:
        assert done.returncode == 0, done.stderr[-3000:]
    return done


def _train_final_weights(store_path: Path, out: Path, processes: int, static: bool) -> dict[str, Any]:
    _train(store_path, out, processes, static)
    return json.loads((out / "r.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("static", [False, True])
def test_two_process_ddp_on_gloo(store_path, tmp_path, static):
    """Two CPU processes (gloo) draw different windows; their gradients are averaged, so both end with the same
    weights, and those differ from one process's trained on rank 0's windows alone (the same stream: the sampler is
    seeded by rank). Rank 0 writes the output. Both the reference and the static-shape path."""
    report = _train_final_weights(store_path, tmp_path / "ddp", 2, static)
    assert report["processes"] == 2
    rank0, rank1 = (load_file(tmp_path / "ddp" / f"rank{k}.safetensors") for k in (0, 1))
    shipped = load_file(tmp_path / "ddp" / "m" / "last.safetensors")  # rank 0's last step, as the stage saved it
    assert rank0.keys() == rank1.keys() == shipped.keys()
    assert all(torch.equal(rank0[k], shipped[k]) for k in rank0)
    assert [k for k in rank0 if not torch.equal(rank0[k], rank1[k])] == []
    alone = _train_final_weights(store_path, tmp_path / "alone", 1, static)
    assert alone["processes"] == 1
    single = load_file(tmp_path / "alone" / "rank0.safetensors")
    moved = max(float((single[k] - rank0[k]).abs().max()) for k in rank0)
    assert moved > 1e-5, "two processes ended where one does on rank 0's windows: rank 1 drew the same windows"


@pytest.mark.slow
def test_two_process_run_in_chunks_resumes_exactly(store_path, tmp_path):
    """Two processes, 4 steps straight vs. stopped after 2 and resumed: the same weights on both ranks, bit for bit.
    Input noise on, so each rank's own RNG stream must come back as well as its window stream."""
    noisy = ("train.input_noise_m=0.0001", "train.checkpoint_every_steps=1")
    _train(store_path, tmp_path / "straight", 2, True, steps=4, overrides=noisy)
    chunk = tmp_path / "chunked"
    first = _train(store_path, chunk, 2, True, steps=4, overrides=noisy, extra=("--stop-at-step", "2"), check=False)
    state = torch.load(chunk / "m.partial" / "last_state.pt", weights_only=False)
    assert state["step"] == 2 and len(state["ranks"]) == 2, first.stderr[-2000:]
    assert state["ranks"][0]["sampler"] != state["ranks"][1]["sampler"]
    _train(store_path, chunk, 2, True, steps=4, overrides=noisy, extra=("--resume",))
    for k in (0, 1):
        straight, resumed = (load_file(d / f"rank{k}.safetensors") for d in (tmp_path / "straight", chunk))
        assert [n for n in straight if not torch.equal(straight[n], resumed[n])] == [], f"rank {k}"


def test_ranks_share_each_steps_layout_but_not_its_windows(store_path, params):
    """Under DDP every rank steps through the same layout (one static step, one captured all-reduce) with its own
    windows; alone, one stream draws both, as before."""
    store = TrajectoryStore(store_path)
    windows = windows_of(phases_of(store, "train"), 5)
    groups = {w.phase.layout for w in windows}
    assert len(groups) > 1, "the synthetic store needs several layouts for this test"
    ranks = [iter(LayoutBatchSampler(windows, 3, seed=4, rank=r, shared_layouts=True)) for r in (0, 1)]
    draws = [[next(s) for _ in range(30)] for s in ranks]
    layout_of = [[windows[b[0]].phase.layout for b in d] for d in draws]
    assert layout_of[0] == layout_of[1] and len(set(layout_of[0])) > 1
    assert draws[0] != draws[1]
    alone, again = (LayoutBatchSampler(windows, 3, seed=4) for _ in range(2))
    state = alone.state()
    assert "layouts" not in state
    again.set_state(state)
    with pytest.raises(ValueError, match="number of processes"):
        LayoutBatchSampler(windows, 3, seed=4, shared_layouts=True).set_state(state)
    assert np.array_equal(next(iter(alone)), next(iter(again)))


def test_a_state_resumes_only_with_its_process_count():
    state = {"ranks": [{"sampler": {"k": 0}, "rng": {}}, {"sampler": {"k": 1}, "rng": {}}]}
    assert rank_streams(state, Processes(1, 2, torch.device("cpu")))["sampler"] == {"k": 1}
    with pytest.raises(ValueError, match="saved by 2 process.*resumed with 1.*nproc-per-node 2"):
        rank_streams(state, Processes(0, 1, torch.device("cpu")))
    old = {"sampler": {"k": 0}, "rng": {"torch": None}}  # saved before per-rank streams
    assert rank_streams(old, Processes(0, 1, torch.device("cpu")))["sampler"] == {"k": 0}


@pytest.mark.slow
def test_scaling_benchmark_reports_each_process_count(store_path, tmp_path):
    """benchmarks/train_scaling.py on 1 and 2 CPU processes: a row each with its efficiency against one process and
    a validation curve at the same sample counts (the params' own base.steps does not change them); the table and the
    chart are written."""
    cmd = [sys.executable, "-m", "benchmarks.train_scaling", "--store", str(store_path), "--procs", "1,2",
           "--samples", "8", "--batch", "2", "--evals", "2", "--tag", "cpu_check", "--out-dir", str(tmp_path),
           *(a for o in ("train.init_from=''", "train.val_windows=1", "train.rollout_frames=2",
                         "train.base.steps=1", "train.base.warmup_steps=0")
             for a in ("--set", o))]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((tmp_path / "train_scaling_cpu_check.json").read_text())
    one, two = report["rows"]
    assert (one["gpus"], two["gpus"]) == (1, 2) and "error" not in two, two.get("error")
    assert one["efficiency"] == pytest.approx(1.0) and (one["lr_factor"], two["lr_factor"]) == (1.0, 2.0)
    assert two["efficiency"] == pytest.approx(two["samples_per_s"] / (2 * one["samples_per_s"]))
    assert [p["samples"] for p in one["val_curve"]] == [p["samples"] for p in two["val_curve"]] == [4, 8]
    assert (tmp_path / "train_scaling_cpu_check.png").stat().st_size > 0
    assert "K=2" in (tmp_path / "train_scaling_cpu_check.md").read_text()
