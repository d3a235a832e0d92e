"""The static-shape training path: the same loss and gradients as the reference path, no graph break under
torch.compile, neighbour overflow grows the capacities instead of dropping pairs, and a run stopped early
resumes to exactly the weights of an uninterrupted run."""

from __future__ import annotations

import copy
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from wc.train.train_stage import run
from tests.conftest import default_params
from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.padded_neighbors import NeighborCapacity
from torch._dynamo.utils import counters

from wc.model.rollout import compiled, frame_step
from wc.model.worldcontact import WorldContact
from wc.config import load_section
from wc.train.capacity import data_capacities
from wc.train.config import TrainConfig
from wc.train.data import phases_of, windows_of
from wc.train.evaluation import segment_loss
from wc.train.loop import SegmentRollout, _layouts
from wc.train.noise import noisy_state
from wc.train.resident import ResidentWindows
from wc.train.static_step import LayoutStep, StaticTrainer, StepSettings

EPISODES = [("fall", "train"), ("carry", "train"), ("handoff", "train"), ("fall", "val")]
TINY_TRAIN = {"base": {"steps": 4, "peak_lr": 1e-3, "start_lr": 1e-4, "final_lr": 1e-4, "warmup_steps": 1},
              "projection": {"steps": 2, "peak_lr": 1e-4, "start_lr": 1e-5, "final_lr": 1e-5, "warmup_steps": 1},
              "eval_every_steps": 2, "val_windows": 2, "rollout_frames": 3, "checkpoint_every_steps": 100,
              "constraint_iterations": 6, "batch_size": 2}


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    return default_params(TINY_TRAIN)


@pytest.fixture(scope="module")
def store_path(synthetic_store, params) -> Path:
    return synthetic_store(params, EPISODES, frames=10)


@pytest.fixture(scope="module")
def setting(store_path, params):
    """Model, layout, resident frames of the first train layout and data capacities."""
    store = TrajectoryStore(store_path)
    model_cfg = load_section(params, "model", ModelConfig)
    cfg = load_section(params, "train", TrainConfig)
    phases = phases_of(store, "train")
    windows = windows_of(phases, cfg.window)
    layout_for = _layouts(store, model_cfg, torch.device("cpu"))
    resident = ResidentWindows(store, windows, cfg.window, torch.device("cpu"))
    capacities, measured = data_capacities(store, phases, model_cfg, layout_for, 1.5, torch.device("cpu"))
    return store, model_cfg, cfg, resident, layout_for, capacities, measured


def _gradients(model: torch.nn.Module) -> list[torch.Tensor]:
    return [p.grad.clone() if p.grad is not None else torch.zeros_like(p) for p in model.parameters()]


def _reference(model: WorldContact, layout, x, v, poses, dt: float, projection, cfg: TrainConfig):  # noqa: ANN001
    model.zero_grad(set_to_none=True)
    x0, v0 = noisy_state(x[:, 0], v[:, 0], cfg.input_noise_m, dt)
    xp, vp = SegmentRollout(model)(layout, x0, v0, poses, dt, projection)
    loss = segment_loss(xp, vp, x[:, 1:], v[:, 1:], cfg.lambda_x, cfg.lambda_v)
    loss.backward()
    return float(loss.detach()), _gradients(model)


def _flat(tensors: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat([t.flatten() for t in tensors])


def _relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@pytest.mark.slow
@pytest.mark.parametrize("stage,tokenizer,noise", [("base", "contact", 0.0), ("projection", "contact", 0.0),
                                                   ("base", "linear", 0.0), ("base", "contact", 3e-4)])
def test_static_step_matches_the_reference_loss_and_gradients(setting, stage, tokenizer, noise):
    store, model_cfg, cfg, resident, layout_for, capacities, _ = setting
    model_cfg = replace(model_cfg, tokenizer=tokenizer)
    cfg = replace(cfg, input_noise_m=noise)
    torch.manual_seed(1)
    model = WorldContact(model_cfg, velocity_m_s=0.3, delta_x_m=0.005, delta_v_m_s=0.1).train()
    torch.nn.init.normal_(model.head.mlp[-1].weight, std=0.05)  # motion large enough to change neighbours
    layout = layout_for(resident.layout_keys[0])
    frames = resident.layouts[0]
    projection = model.projection(layout, constraint_iterations=cfg.constraint_iterations) if stage == "projection" \
        else None
    starts = np.array([0, 3])
    x, v, poses = frames.gather(torch.from_numpy(starts), cfg.window)
    torch.manual_seed(7)
    want_loss, want_grads = _reference(model, layout, x, v, poses, store.dt, projection, cfg)

    optimizer = torch.optim.AdamW(model.parameters(), lr=0.0)
    step = LayoutStep(model, SegmentRollout(model), optimizer, layout, frames, model.fixed_neighbors(layout, capacities),
                      projection, StepSettings.of(cfg, store.dt))
    torch.manual_seed(7)  # the same dropout masks
    loss, overflow = step.forward_backward(starts).tolist()
    assert overflow == 0
    assert loss == pytest.approx(want_loss, rel=1e-5) and want_loss > 0
    got = _gradients(model)
    assert _relative(_flat(got), _flat(want_grads)) < 1e-5  # ‖g − g_ref‖ / ‖g_ref‖ over all parameters
    for (name, _), g, w in zip(model.named_parameters(), got, want_grads):
        assert (float(g.norm()) == 0.0) == (float(w.norm()) == 0.0), name  # the same parameters learn


@pytest.mark.slow
def test_overflow_grows_the_capacities_and_reruns_the_batch(setting):
    store, model_cfg, cfg, resident, layout_for, capacities, _ = setting
    torch.manual_seed(2)
    model = WorldContact(replace(model_cfg, dropout=0.0), velocity_m_s=0.3, delta_x_m=0.005, delta_v_m_s=0.1)
    layout, frames = layout_for(resident.layout_keys[0]), resident.layouts[0]
    starts = np.array([1, 2])
    x, v, poses = frames.gather(torch.from_numpy(starts), cfg.window)
    want_loss, _ = _reference(model, layout, x, v, poses, store.dt, None, cfg)
    tiny = {name: NeighborCapacity(1, 1) for name in capacities}
    optimizer = torch.optim.AdamW(model.parameters(), lr=0.0)
    trainer = StaticTrainer(model, SegmentRollout(model), optimizer, tiny, StepSettings.of(cfg, store.dt))
    loss = trainer.step(0, layout, frames, starts, None, step_number=0)
    assert trainer.grown and trainer.grown[0]["step"] == 0 and trainer.grown[0]["overflow"]
    assert loss == pytest.approx(want_loss, rel=1e-5)  # nothing was dropped in the step that counted
    assert all(c.max_neighbors > 1 for c in trainer.capacities.values())


@pytest.mark.slow
def test_frame_step_compiles_once_for_every_layout_without_a_graph_break(setting):
    """fullgraph=True fails on any host sync or data-dependent shape in the step; with symbolic sizes one graph serves
    layouts of different vertex counts (and batch sizes), forward and backward, and matches eager."""
    store, model_cfg, cfg, resident, layout_for, capacities, _ = setting
    torch.manual_seed(3)
    model = WorldContact(replace(model_cfg, dropout=0.0), velocity_m_s=0.3, delta_x_m=0.005, delta_v_m_s=0.1)
    torch._dynamo.reset()
    counters.clear()  # reset() keeps the counters: graphs compiled by earlier tests in this process would count
    sizes = set()
    two_objects = resident.layout_keys.index(next(k for k in resident.layout_keys if len(k[0]) > 1))
    for index, batch in ((0, 3), (two_objects, 2)):  # other vertex counts, another batch size (not 1: torch
        # specialises sizes 0 and 1)
        layout, frames = layout_for(resident.layout_keys[index]), resident.layouts[index]
        sizes.add(layout.num_vertices)
        projection = model.projection(layout, constraint_iterations=2)
        step = frame_step(model, layout, store.dt, projection, model.fixed_neighbors(layout, capacities))
        starts = torch.from_numpy(resident.window_start[resident.window_layout == index]).repeat(batch)[:batch]
        x, v, poses = frames.gather(starts, cfg.window)
        results = []
        for fn in (step, compiled(step, backend="aot_eager")):
            model.zero_grad(set_to_none=True)
            xn, vn = fn(x[:, 0], v[:, 0], poses[:, 0], poses[:, 1])
            (xn.square().sum() + vn.square().sum()).backward()
            results.append((xn.detach(), _gradients(model)))
        torch.testing.assert_close(results[1][0], results[0][0], rtol=1e-5, atol=1e-7)
        assert _relative(_flat(results[1][1]), _flat(results[0][1])) < 1e-5
    assert len(sizes) == 2
    assert counters["stats"]["unique_graphs"] == 1  # the second layout reused the first one's graph


def _static_params(params: dict[str, Any]) -> dict[str, Any]:
    p = copy.deepcopy(params)
    p["train"]["static"] = True
    return p


@pytest.mark.slow
@pytest.mark.parametrize("static", [True, False])
def test_a_stopped_run_resumes_to_the_uninterrupted_result(store_path, params, tmp_path, static):
    p = _static_params(params) if static else copy.deepcopy(params)
    whole = run(p, store_path, tmp_path / "whole", tmp_path / "w.json", tmp_path / "w.csv")
    cut = run(p, store_path, tmp_path / "cut", tmp_path / "c.json", tmp_path / "c.csv", stop_at_step=3)
    assert cut["complete"] is False and cut["step"] == 3
    assert (tmp_path / "cut.partial" / "last_state.pt").is_file() and not (tmp_path / "cut").exists()
    resumed = run(p, store_path, tmp_path / "cut", tmp_path / "c.json", tmp_path / "c.csv", resume=True)
    assert resumed["history"] == whole["history"]  # validation and train losses, learning rates
    a = torch.load(tmp_path / "whole" / "last_state.pt", weights_only=False)
    b = torch.load(tmp_path / "cut" / "last_state.pt", weights_only=False)
    for name, tensor in a["model"].items():
        assert torch.equal(tensor, b["model"][name]), name
    if static:
        assert resumed["capacities"] == whole["capacities"]


@pytest.mark.slow
def test_max_minutes_stops_with_a_complete_checkpoint(store_path, params, tmp_path):
    p = _static_params(params)
    p["train"]["max_minutes"] = 1e-9  # out of time after the first step
    report = run(p, store_path, tmp_path / "m", tmp_path / "r.json", tmp_path / "c.csv")
    assert report["complete"] is False and report["step"] == 1
    state = torch.load(tmp_path / "m.partial" / "last_state.pt", weights_only=False)
    assert state["step"] == 1 and {"model", "optimizer", "ranks", "capacities"} <= set(state)
    assert len(state["ranks"]) == 1 and {"sampler", "rng"} <= set(state["ranks"][0])  # one process: one rank's streams
    assert not (tmp_path / "r.json").exists()


def test_input_noise_is_a_consistent_random_walk():
    """x gets noise of std σ; the frame before it, x - v·Δt, gets σ/√2 (the walk's first step): x and v stay the
    state of a noisy trajectory."""
    torch.manual_seed(0)
    x, v = torch.randn(4, 50_000, 3), torch.randn(4, 50_000, 3)
    same = noisy_state(x, v, 0.0, 0.04)
    assert same[0] is x and same[1] is v
    sigma, dt = 1e-3, 0.04
    xn, vn = noisy_state(x, v, sigma, dt)
    on_x = (xn - x).std().item()
    on_previous = ((xn - vn * dt) - (x - v * dt)).std().item()
    assert on_x == pytest.approx(sigma, rel=0.02)
    assert on_previous == pytest.approx(sigma / 2**0.5, rel=0.02)
    with pytest.raises(ValueError, match="noise"):
        noisy_state(x, v, -1.0, dt)
