"""The baselines' training-recipe switches (WorldContact's input noise, event oversampling, checkpoint selection by
held-out rollout), recorded in their report beside the losses zero motion and constant velocity would have."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from tests.conftest import load_params
from wc.baselines import build_baseline, load_baseline
from wc.baselines.config import BaselineParams, BaselinesConfig
from wc.baselines.train import reference_particle_losses, train_baseline
from wc.config import ParamsError, load_section
from wc.train.config import TrainConfig
from wc.train.noise import noisy_history

TINY = {"names": ["robocook"], "eval_every_steps": 1, "val_windows": 1, "rollout_frames": 3, "rollout_phases": 1,
        "device": "cpu", "seed": 0,
        "models": {"robocook": {"particles": 12, "steps": 2, "lr": 1e-4, "batch": 1, "neighbor_radius_m": 0.08,
                                "tool_radius_m": 0.05, "max_step_m": 0.02, "tool_points_per_body": 2}}}


@pytest.fixture(scope="module")
def params():
    p = copy.deepcopy(load_params())
    p["baselines"] = copy.deepcopy(TINY)
    return p


@pytest.fixture(scope="module")
def store_path(synthetic_store, params):
    return synthetic_store(params, [("fall", "train"), ("carry", "train"), ("fall", "val"), ("carry", "val")],
                           frames=12)


def test_history_noise_is_a_random_walk_ending_at_its_std():
    torch.manual_seed(0)
    x = torch.zeros(2000, 4, 5, 3)
    noisy = noisy_history(x, 0.01)
    assert noisy[:, -1].std().item() == pytest.approx(0.01, rel=0.05)
    assert noisy[:, 0].std().item() == pytest.approx(0.01 / 2, rel=0.05)  # one step of four: std / sqrt(4)
    assert noisy_history(x, 0.0) is x
    with pytest.raises(ValueError, match=">= 0"):
        noisy_history(x, -1.0)


@pytest.mark.parametrize("name", ["robocraft", "robocook", "adaptigraph"])
def test_reference_losses_score_a_constant_velocity_window_zero(name):
    """Particles moving at one velocity: constant velocity's loss is 0, zero motion's is not (planted bug caught:
    extrapolating from the first observed frame instead of the last)."""
    model = build_baseline(name, BaselineParams(**TINY["models"]["robocook"]))
    torch.manual_seed(0)
    p0 = 0.1 * torch.rand(12, 3)
    frames = model.history + model.sequence
    moving = (p0 + torch.arange(frames)[:, None, None] * torch.tensor([0.01, 0.0, 0.005]))[None]
    zero, constant = reference_particle_losses(model, moving)
    assert constant == pytest.approx(0.0, abs=1e-6) and zero > 1e-5
    still = p0.expand(1, frames, -1, -1)
    assert reference_particle_losses(model, still) == pytest.approx((0.0, 0.0), abs=1e-7)


@pytest.mark.slow
def test_switches_are_recorded_and_rollout_selection_keeps_the_best_rollout(store_path, params, tmp_path):
    train_cfg = dataclasses.replace(load_section(params, "train", TrainConfig), input_noise_m=0.002,
                                    event_oversample=3.0)
    off = load_section(params, "baselines", BaselinesConfig)
    report = train_baseline("robocook", store_path, tmp_path / "off", off, train_cfg)
    assert report["recipe"] == {"input_noise_m": 0.0, "event_oversample": 0.0, "event_window_share": None,
                                "select_by": "val_loss"}
    on = dataclasses.replace(off, input_noise=True, event_oversample=True, select_by="rollout")
    report = train_baseline("robocook", store_path, tmp_path / "on", on, train_cfg)
    assert report["recipe"]["input_noise_m"] == 0.002 and report["recipe"]["event_oversample"] == 3.0
    assert 0.0 <= report["recipe"]["event_window_share"] <= 1.0 and report["recipe"]["select_by"] == "rollout"
    scores = [h["rollout_position_mse_m2"] for h in report["history"]]
    assert report["best_score"] == min(scores) and report["best_step"] == report["history"][int(np.argmin(scores))]["step"]
    for h in report["history"]:  # logged beside every validation loss (the window here may be a bag at rest: 0)
        assert h["val_loss_zero_motion"] == report["val_loss_zero_motion"] >= 0
        assert h["val_loss_constant_velocity"] == report["val_loss_constant_velocity"] >= 0
    assert load_baseline(tmp_path / "on").name == "robocook"


def test_an_unknown_selection_is_named(params):
    with pytest.raises(ParamsError, match="select_by"):
        load_section({**params, "baselines": {**copy.deepcopy(TINY), "select_by": "loss"}}, "baselines",
                     BaselinesConfig)


def test_rollout_selection_keeps_the_best_weights_without_a_patience_rule():
    from wc.baselines.stopping import StopRule  # noqa: PLC0415

    model = torch.nn.Linear(2, 1)
    rule = StopRule(keep_best=True)
    rule.record(1, 0.5, model)
    best = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        model.weight.add_(1.0)
    rule.record(2, 0.9, model)
    rule.restore_best(model)
    assert all(torch.equal(model.state_dict()[k], v) for k, v in best.items()) and not rule.converged()
