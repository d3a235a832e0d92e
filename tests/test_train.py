"""Training WorldContact: windows and phases, schedule, one step lowers the loss, checkpoints reload
exactly, the stage trains below zero motion and resumes, bad input fails clearly, DDP on gloo."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from wc.train.train_stage import run
from tests.conftest import default_params, load_params
from tests.synthetic_store import write_synthetic_store
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.layout import boundary_samples, scene_layout
from wc.model.rollout import rollout
from wc.model.worldcontact import WorldContact
from wc.train.checkpoint import load_model, save_weights
from wc.train.config import Schedule, TrainConfig
from wc.train.data import (LayoutBatchSampler, data_scales, episode_phases, overall, phases_of, read_phase_window,
                           split_blocks, windows_of)
from wc.train.events import event_frames
from wc.train.evaluation import segment_loss
from wc.train.schedule import learning_rate
from wc.train.selection import max_edge_strain, selection_score, shipped_stage

EPISODES = [("fall", "train"), ("carry", "train"), ("handoff", "train"), ("fall", "train"), ("fall", "val"),
            ("carry", "val")]
TINY_TRAIN = {"base": {"steps": 6, "peak_lr": 1e-3, "start_lr": 1e-4, "final_lr": 1e-4, "warmup_steps": 2},
              "projection": {"steps": 2, "peak_lr": 1e-4, "start_lr": 1e-5, "final_lr": 1e-5, "warmup_steps": 1},
              "eval_every_steps": 3, "val_windows": 2, "rollout_frames": 4, "checkpoint_every_steps": 3,
              "constraint_iterations": 8}


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    return default_params(TINY_TRAIN)


@pytest.fixture(scope="module")
def store_path(synthetic_store, params) -> Path:
    return synthetic_store(params, EPISODES, frames=10)


def _batch(store_path: Path, params: dict[str, Any], episode: str = "ep_000000", length: int = 5):
    store = TrajectoryStore(store_path)
    phase = episode_phases(store, episode)[0]
    cfg = load_section(params, "model", ModelConfig)
    layout = scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), cfg.tag_scale)
    a = {k: torch.from_numpy(v)[None] for k, v in read_phase_window(store, phase, 0, length).items()}
    return cfg, layout, a


def test_handoff_episode_splits_into_two_layouts(store_path):
    store = TrajectoryStore(store_path)
    before, after = episode_phases(store, "ep_000002")
    release = store.episode_attrs("ep_000002")["handoff"]["sphere"]
    assert (before.start, before.stop, after.start, after.stop) == (0, release + 1, release, 10)
    assert before.layout[0] == ("bag",) and "held_sphere" in before.layout[1]
    assert after.layout[0] == ("bag", "sphere") and "held_sphere" not in after.layout[1]
    a = read_phase_window(store, before, 0, 3)
    assert a["x"].shape[1] == store.objects["bag"].rest_positions.shape[0]
    assert a["poses"].shape[1] == len(before.layout[1]) + len(store.env_names)
    assert all(w.start + 5 <= w.phase.stop for w in windows_of([before, after], 5))


def test_block_holdout_interleaves_without_sharing_a_frame(store_path):
    store = TrajectoryStore(store_path)
    phases = [p for e in store.episodes_where(split="train") for p in episode_phases(store, e)]
    train, held = split_blocks(phases, 0.5, 3, 3)
    assert held, "a 0.5 holdout of 3-frame blocks must hold something out"
    trains_after_held = False
    for p in phases:
        mine = lambda parts: [q for q in parts if q.episode == p.episode and q.layout == p.layout]  # noqa: E731
        train_frames = {f for q in mine(train) for f in range(q.start, q.stop)}
        held_frames = {f for q in mine(held) for f in range(q.start, q.stop)}
        assert not train_frames & held_frames
        assert train_frames | held_frames <= set(range(p.start, p.stop))
        if held_frames:  # block 0 trains; interleaved: some phase trains after a held block too
            assert min(train_frames) < min(held_frames)
            trains_after_held |= any(f > min(held_frames) for f in train_frames)
    assert trains_after_held
    assert all(q.stop - q.start >= 3 for q in train + held)


def test_schedule_warms_up_then_decays():
    s = Schedule(steps=100, peak_lr=1e-3, start_lr=1e-5, final_lr=1e-4, warmup_steps=10)
    assert learning_rate(s, 0) == pytest.approx(1e-5)
    assert learning_rate(s, 10) == pytest.approx(1e-3)
    assert learning_rate(s, 100) == pytest.approx(1e-4)
    lrs = [learning_rate(s, k) for k in range(10, 101)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))


def test_one_training_step_lowers_the_loss_on_a_fixed_batch(store_path, params):
    torch.manual_seed(0)
    cfg, layout, a = _batch(store_path, params)
    model = WorldContact(cfg, velocity_m_s=0.3, delta_x_m=0.005, delta_v_m_s=0.1).train()
    model.decoder.eval()  # no dropout: the same function before and after the step
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)

    def loss() -> torch.Tensor:
        xp, vp = rollout(model, layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
        return segment_loss(xp, vp, a["x"][:, 1:], a["v"][:, 1:], 1e4, 1e4)

    before = loss()
    opt.zero_grad()
    before.backward()
    opt.step()
    with torch.no_grad():
        assert float(loss()) < float(before)


@pytest.mark.parametrize("mode", ["integrate", "direct"])
def test_position_update_modes(store_path, params, mode):
    """"integrate": X̂ = X + Δt·V̂ + ΔX (positions follow the predicted velocity); "direct": X̂ = X + ΔX."""
    from dataclasses import replace

    from wc.model.layout import boundary_samples
    from wc.model.worldcontact import advance
    cfg, layout, a = _batch(store_path, params)
    model = WorldContact(replace(cfg, position_update=mode), velocity_m_s=0.3, delta_x_m=0.005,
                         delta_v_m_s=0.1).eval()
    x, v = a["x"][:, 0], a["v"][:, 0]
    controllable, environment = boundary_samples(layout, a["poses"][:, 0], a["poses"][:, 1], 0.04)
    with torch.no_grad():
        dx, dv = model(x, v, layout, controllable, environment)
        x1, v1 = advance(model, x, v, layout, controllable, environment, 0.04)
    torch.testing.assert_close(v1, v + dv)
    torch.testing.assert_close(x1, x + dx + 0.04 * v1 if mode == "integrate" else x + dx)
    with pytest.raises(ValueError, match="position_update"):
        replace(cfg, position_update="euler").validate()


def test_checkpoint_reloads_to_identical_predictions(store_path, params, tmp_path):
    cfg, layout, a = _batch(store_path, params)
    model = WorldContact(cfg, velocity_m_s=0.3, delta_x_m=0.005, delta_v_m_s=0.1).eval()
    torch.nn.init.normal_(model.head.mlp[-1].weight, std=0.1)  # visible predictions
    save_weights(model, tmp_path / "m.safetensors", {"note": "test"})
    loaded, meta = load_model(tmp_path / "m.safetensors")
    assert meta["note"] == "test"
    with torch.no_grad():
        want = rollout(model, layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
        got = rollout(loaded, layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
    assert torch.equal(want[0], got[0]) and torch.equal(want[1], got[1])


def test_per_axis_scales_scale_each_axis_and_survive_a_checkpoint(store_path, params, tmp_path):
    cfg, layout, a = _batch(store_path, params)
    torch.manual_seed(0)
    axes = WorldContact(cfg, velocity_m_s=(0.3, 0.3, 0.6), delta_x_m=(0.005, 0.005, 0.02), delta_v_m_s=0.1).eval()
    torch.nn.init.normal_(axes.head.mlp[-1].weight, std=0.1)
    one = WorldContact(cfg, velocity_m_s=(0.3, 0.3, 0.6), delta_x_m=0.005, delta_v_m_s=0.1).eval()
    one.load_state_dict(axes.state_dict() | {"scales": one.scales})
    args = (a["x"][:, 0], a["v"][:, 0], layout, *boundary_samples(layout, a["poses"][:, 0], a["poses"][:, 1], 0.04))
    with torch.no_grad():
        dx_axes, _ = axes(*args)
        dx_one, _ = one(*args)
    torch.testing.assert_close(dx_axes[..., :2], dx_one[..., :2])  # same network, x and y scaled alike ...
    torch.testing.assert_close(dx_axes[..., 2], 4 * dx_one[..., 2])  # ... z by its own scale, 4x here
    save_weights(axes, tmp_path / "a.safetensors", {})
    assert json.loads((tmp_path / "a.json").read_text())["scales"]["delta_x_m"] == pytest.approx([0.005, 0.005, 0.02])
    loaded, _ = load_model(tmp_path / "a.safetensors")
    assert torch.equal(loaded.scales, axes.scales)
    with pytest.raises(ValueError, match="delta_x_m must be one positive value or three"):
        WorldContact(cfg, velocity_m_s=0.3, delta_x_m=(0.1, 0.2), delta_v_m_s=0.1)


def test_a_checkpoint_saved_with_one_scale_per_quantity_still_loads(store_path, params, tmp_path):
    cfg, _, _ = _batch(store_path, params)
    model = WorldContact(cfg, velocity_m_s=0.3, delta_x_m=0.005, delta_v_m_s=0.1)
    save_weights(model, tmp_path / "m.safetensors", {})
    from safetensors.torch import load_file, save_file
    state = load_file(str(tmp_path / "m.safetensors"))
    save_file(state | {"scales": torch.tensor([0.3, 0.005, 0.1])}, str(tmp_path / "m.safetensors"))  # the old (3,)
    loaded, _ = load_model(tmp_path / "m.safetensors")
    torch.testing.assert_close(loaded.scales, model.scales)


def test_per_axis_data_scales_agree_with_the_single_scale(store_path):
    store = TrajectoryStore(store_path)
    phases = [p for e in store.episode_ids for p in episode_phases(store, e)]
    single, axes = data_scales(store, phases, 8), data_scales(store, phases, 8, per_axis=True)
    for name in ("velocity_m_s", "delta_x_m", "delta_v_m_s"):
        assert len(getattr(axes, name)) == 3
        assert overall(getattr(axes, name)) == pytest.approx(getattr(single, name), rel=1e-6)


def test_corrupt_or_missing_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_model(tmp_path / "none.safetensors")
    (tmp_path / "bad.safetensors").write_bytes(b"not a tensor file")
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="not a WorldContact checkpoint config"):
        load_model(tmp_path / "bad.safetensors")


def test_bad_model_inputs_are_named(store_path, params):
    cfg, layout, a = _batch(store_path, params)
    model = WorldContact(cfg, velocity_m_s=0.3, delta_x_m=0.005, delta_v_m_s=0.1)
    x, v = a["x"][:, 0], a["v"][:, 0]
    with pytest.raises(ValueError, match="x must be"):
        rollout(model, layout, x[:, :-1], v[:, :-1], a["poses"], 0.04)  # object set of another layout
    with pytest.raises(ValueError, match="body poses"):
        rollout(model, layout, x, v, a["poses"][:, :, :-1], 0.04)
    bad = x.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        rollout(model, layout, bad, v, a["poses"], 0.04)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, store_path, params) -> tuple[dict[str, Any], Path]:
    d = tmp_path_factory.mktemp("train")
    report = run(params, store_path, d / "model", d / "train.json", d / "train_loss.csv")
    return report, d


@pytest.mark.slow
def test_stage_writes_model_report_and_curves(trained):
    report, d = trained
    assert json.loads((d / "train.json").read_text())["params_hash"] == report["params_hash"]
    assert report["parameters"] == {"tokenizer": 57993, "encoder": 782784, "decoder": 1116480, "head": 42502,
                                    "total": 1999759}
    assert report["validation"] == "val split"
    by_stage = report["best_val_loss_by_stage"]  # the stage that validates better ships
    assert set(by_stage) == {"base", "projection"}
    assert report["final_stage"] == min(by_stage, key=by_stage.get)
    assert report["best_val_loss"] == by_stage[report["final_stage"]]
    assert [h["step"] for h in report["history"]] == [3, 6, 8]
    assert {h["stage"] for h in report["history"]} == {"base", "projection"}
    for name in ("model", "base", "last"):
        assert (d / "model" / f"{name}.safetensors").is_file() and (d / "model" / f"{name}.json").is_file()
    assert not Path(f"{d / 'model'}.partial").exists()
    assert (d / "train_loss.png").stat().st_size > 0 and len((d / "train_loss.csv").read_text().splitlines()) == 4
    model, meta = load_model(d / "model" / "model.safetensors")
    assert meta["stage"] == report["final_stage"] and meta["projection"] is (report["final_stage"] == "projection")
    # below zero motion on the same validation windows; and trained: the base stage's best evaluation beats its first
    # (an untrained model, near constant velocity, is already below zero motion on these windows)
    assert report["best_val_loss"] < report["zero_motion_val_loss"]
    assert by_stage["base"] < report["history"][0]["val_loss"]


@pytest.mark.slow
def test_resume_continues_from_the_partial_checkpoint(store_path, params, tmp_path):
    first = copy.deepcopy(params)
    first["train"]["base"]["steps"] = 3
    first["train"]["projection"].update(steps=0, warmup_steps=0)
    out = tmp_path / "model"
    run(first, store_path, out, tmp_path / "a.json", tmp_path / "a.csv")
    (tmp_path / "model").rename(tmp_path / "model.partial")  # as if interrupted after step 3
    second = copy.deepcopy(params)
    second["train"]["projection"].update(steps=0, warmup_steps=0)
    report = run(second, store_path, out, tmp_path / "b.json", tmp_path / "b.csv", resume=True)
    assert [h["step"] for h in report["history"]] == [3, 6]


def test_edge_strain_and_selection_scores():
    x = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 2.0, 0.0]]])  # edges at rest lengths 1, 1
    edges, rest = torch.tensor([[0, 1], [1, 2]]), torch.tensor([1.0, 1.0])
    assert max_edge_strain(x, edges, rest) == pytest.approx(1.0)  # the second edge doubled
    assert max_edge_strain(x * float("nan"), edges, rest) == float("inf")
    good = {"val_loss": 5.0, "rollout_position_mse_m2": 1e-4, "rollout_diverged": 0}
    assert selection_score(good, "val_loss") == 5.0 and selection_score(good, "rollout") == 1e-4
    assert selection_score({**good, "rollout_diverged": 1}, "rollout") == float("inf")
    assert selection_score({**good, "rollout_position_mse_m2": float("nan")}, "rollout") == float("inf")


def test_the_shipped_stage_is_the_better_scored_or_the_last_that_ran():
    scores = {"base": 12.0, "projection": 15.0}  # the projection's corrections cost it on windows
    assert shipped_stage(scores, "best") == "base" and shipped_stage(scores, "last") == "projection"
    assert shipped_stage({"base": 12.0}, "last") == "base"  # no projection steps: the base stage is the last
    with pytest.raises(ValueError, match="ship_stage must be one of"):
        shipped_stage(scores, "final")
    with pytest.raises(ValueError, match="ship_stage must be one of"):
        load_section(load_params("train.ship_stage=final"), "train", TrainConfig)


@pytest.mark.slow
def test_ship_stage_last_ships_the_projection_stage(store_path, params, tmp_path):
    """Whatever the scores, `last` ships the projection stage's best checkpoint, which applies the projection."""
    p = copy.deepcopy(params)
    p["train"]["ship_stage"] = "last"
    report = run(p, store_path, tmp_path / "m", tmp_path / "r.json", tmp_path / "c.csv")
    assert report["final_stage"] == "projection"
    _, meta = load_model(tmp_path / "m" / "model.safetensors")
    assert meta["stage"] == "projection" and meta["projection"] is True


@pytest.mark.slow
def test_rollout_selection_ships_the_best_held_out_rollout_never_a_diverged_one(store_path, params, tmp_path):
    """select_by rollout: the shipped checkpoint is the evaluation with the lowest held-out rollout MSE among those
    that did not diverge; a strain limit every rollout breaks leaves each stage its first checkpoint, scored inf."""
    p = copy.deepcopy(params)
    p["train"].update(select_by="rollout", eval_every_steps=2)
    report = run(p, store_path, tmp_path / "m", tmp_path / "r.json", tmp_path / "c.csv")
    history = report["history"]
    assert report["selected_by"] == "rollout" and all("rollout_max_strain" in h for h in history)
    finite = [h for h in history if h["rollout_diverged"] == 0]
    assert finite, "no evaluation without a diverged rollout on the tiny store"
    best = min(finite, key=lambda h: h["rollout_position_mse_m2"])
    assert report["best_score"] == best["rollout_position_mse_m2"] and report["final_stage"] == best["stage"]
    _, meta = load_model(tmp_path / "m" / "model.safetensors")
    assert meta["step"] == best["step"] == report["selected"]["step"]

    strict = copy.deepcopy(p)
    strict["train"]["select_max_strain"] = 1e-9  # every rollout "diverges"
    report = run(strict, store_path, tmp_path / "s", tmp_path / "s.json", tmp_path / "s.csv")
    assert all(h["rollout_diverged"] > 0 and h["score"] == float("inf") for h in report["history"])
    _, meta = load_model(tmp_path / "s" / "model.safetensors")
    assert meta["step"] == min(h["step"] for h in report["history"] if h["stage"] == report["final_stage"])


def test_rollout_selection_needs_whole_held_out_episodes(params, tmp_path):
    store = write_synthetic_store(tmp_path / "s.zarr", params, [("fall", "train"), ("carry", "train")], frames=10)
    p = copy.deepcopy(params)
    p["train"]["select_by"] = "rollout"
    with pytest.raises(ValueError, match="no val split"):
        run(p, store, tmp_path / "m", tmp_path / "r.json", tmp_path / "c.csv")
    p["train"]["select_by"] = "best_guess"
    with pytest.raises(ParamsError, match="select_by"):
        load_section(p, "train", TrainConfig)


def test_contact_events_are_gripper_moves_and_impacts():
    action = np.zeros((10, 14))
    action[4:, 13] = 0.01  # the right pads close between frames 3 and 4
    v = np.zeros((10, 5, 3))
    v[7:, 2, 2] = 0.5  # one vertex jumps by 0.5 m/s between frames 6 and 7: 12.5 m/s^2 at dt 0.04
    events = event_frames(action, v, 0.04, accel_m_s2=8.0)
    assert np.flatnonzero(events).tolist() == [4, 7]
    assert np.flatnonzero(event_frames(action, v, 0.04, accel_m_s2=20.0)).tolist() == [4]


def test_weighted_sampler_oversamples_and_checks_its_weights(store_path):
    store = TrajectoryStore(store_path)
    windows = windows_of([p for e in store.episode_ids for p in episode_phases(store, e)], 5)
    weights = np.ones(len(windows))
    weights[0] = 50.0
    draws = LayoutBatchSampler(windows, 4, seed=0, weights=weights)
    counts = np.bincount(np.concatenate([next(iter(draws)) for _ in range(400)]), minlength=len(windows))
    same_layout = [i for i, w in enumerate(windows) if w.phase.layout == windows[0].phase.layout]
    assert counts[0] > 10 * np.mean(counts[same_layout[1:]])
    with pytest.raises(ValueError, match="positive"):
        LayoutBatchSampler(windows, 4, seed=0, weights=np.zeros(len(windows)))


@pytest.mark.slow
def test_event_oversampling_in_a_training_run(store_path, params, tmp_path):
    p = copy.deepcopy(params)
    p["train"].update(event_oversample=3.0, event_accel_m_s2=1.0)
    p["train"]["projection"].update(steps=0, warmup_steps=0)
    report = run(p, store_path, tmp_path / "m", tmp_path / "r.json", tmp_path / "c.csv")
    cfg, store = load_section(p, "train", TrainConfig), TrajectoryStore(store_path)
    margin, near = cfg.event_margin_frames, []
    for w in windows_of(phases_of(store, "train"), cfg.window):  # an event frame within the margin of the window
        phase = w.phase
        a = read_phase_window(store, phase, phase.start, phase.stop - phase.start)
        events = np.flatnonzero(event_frames(a["action"], a["v"], store.dt, cfg.event_accel_m_s2)) + phase.start
        near.append(bool(((events >= w.start - margin) & (events <= w.start + cfg.window - 1 + margin)).any()))
    assert 0 < sum(near) < len(near)  # the data have windows near an event and windows far from any
    assert report["event_window_share"] == pytest.approx(np.mean(near))
    p["train"]["event_oversample"] = -1.0
    with pytest.raises(ParamsError, match="event_oversample"):
        load_section(p, "train", TrainConfig)


def test_missing_store_and_bad_params(params, tmp_path):
    with pytest.raises(FileNotFoundError, match="trajectory store not found"):
        run(params, tmp_path / "none.zarr", tmp_path / "m", tmp_path / "r.json", tmp_path / "c.csv")
    bad = copy.deepcopy(params)
    bad["train"]["window"] = 1
    with pytest.raises(ParamsError, match="window"):
        run(bad, tmp_path / "none.zarr", tmp_path / "m", tmp_path / "r.json", tmp_path / "c.csv")
    bad = copy.deepcopy(params)
    bad["model"]["tokenizer"] = "mlp"
    with pytest.raises(ParamsError, match="model.tokenizer"):
        load_section(bad, "model", ModelConfig)
    load_section(params, "train", TrainConfig)
