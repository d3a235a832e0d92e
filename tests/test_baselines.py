"""Baselines (RoboCraft, RoboCook, AdaptiGraph): shapes, one step lowers the loss, the exact map back to
vertices, set losses, save/load, the pruned PropNet against the dense one, and the stage on a synthetic store."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from wc.baselines.baselines_stage import run
from tests.conftest import load_params
from wc.baselines import BASELINES, base, build_baseline, load_baseline, save_baseline
from wc.baselines.config import BaselineParams, BaselinesConfig
from wc.baselines.stopping import StopRule
from wc.baselines.train import train_baseline
from wc.baselines.losses import chamfer, emd
from wc.baselines.propnet import PropNet
from wc.baselines.sampling import particle_map
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.model.layout import SceneLayout, boundary_samples, scene_layout
from wc.train.config import TrainConfig
from wc.train.data import episode_phases, read_phase_window

EPISODES = [("fall", "train"), ("carry", "train"), ("fall", "train"), ("fall", "val"), ("carry", "val")]
TINY = {"names": list(BASELINES), "eval_every_steps": 2, "val_windows": 1, "rollout_frames": 3, "rollout_phases": 1,
        "device": "cpu", "seed": 0,
        "models": {"robocraft": {"particles": 12, "steps": 2, "lr": 1e-4, "batch": 1, "neighbor_radius_m": 0.08,
                                 "tool_radius_m": 0.02, "max_step_m": 0.025, "tool_points_per_body": 2},
                   "robocook": {"particles": 12, "steps": 2, "lr": 1e-4, "batch": 1, "neighbor_radius_m": 0.08,
                                "tool_radius_m": 0.05, "max_step_m": 0.02, "tool_points_per_body": 2},
                   "adaptigraph": {"particles": 12, "steps": 2, "lr": 1e-3, "batch": 1, "neighbor_radius_m": 0.1,
                                   "tool_points_per_body": 2}}}
# every tool point touches the bag: RoboCraft takes its non-rigid head, RoboCook does not zero its output
WIDE = {"neighbor_radius_m": 0.1, "tool_radius_m": 2.0, "max_step_m": 1.0}


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    p = load_params()
    p["baselines"] = copy.deepcopy(TINY)
    return p


@pytest.fixture(scope="module")
def store_path(synthetic_store, params) -> Path:
    return synthetic_store(params, EPISODES, frames=12)


def _window(store_path: Path, episode: str, length: int):
    store = TrajectoryStore(store_path)
    phase = episode_phases(store, episode)[0]
    layout = scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), 1.0)
    a = {k: torch.from_numpy(v)[None] for k, v in read_phase_window(store, phase, 0, length).items()}
    return layout, a


def _model(name: str, **overrides: Any):
    params = BaselineParams(**{**TINY["models"][name], **overrides})
    torch.manual_seed(0)
    model = build_baseline(name, params)
    model.set_statistics(torch.tensor([0.0, 0.0, 0.05]), torch.tensor([0.05, 0.03, 0.04]), 0.004)
    return model


def _dense_effects(net: PropNet, nodes: torch.Tensor, relations: torch.Tensor, receivers: torch.Tensor,
                   senders: torch.Tensor) -> torch.Tensor:
    """Reference: PropNet effects of every node, propagated over every node as in the originals."""
    particle_enc = net.particle_encoder(nodes)
    relation_enc = net.relation_encoder(relations)
    effect = torch.zeros_like(particle_enc)
    for _ in range(net.pstep):
        rel = torch.relu(net.relation_propagator(torch.cat([relation_enc, effect[receivers], effect[senders]], -1)))
        agg = torch.zeros_like(effect).index_add_(0, receivers, rel)
        effect = torch.relu(net.particle_propagator(torch.cat([particle_enc, agg], -1)) + effect)
    return effect


def _all_sample_frames(layout: SceneLayout, poses: torch.Tensor, rows: torch.Tensor):
    """Reference: every prescribed sample posed by boundary_samples, then the rows taken."""
    b, t = poses.shape[:2]
    flat = poses.reshape(b * t, *poses.shape[2:])
    controllable, environment = boundary_samples(layout, flat, flat, 1.0)
    x = torch.cat([controllable.x, environment.x], 1).reshape(b, t, -1, 3)
    n = torch.cat([controllable.attributes[..., 1:], environment.attributes[..., 1:]], 1).reshape(b, t, -1, 3)
    return x[:, :, rows], n[:, :, rows]


def test_propnet_matches_the_dense_reference_and_ignores_nodes_that_send_nothing():
    torch.manual_seed(0)
    net = PropNet(4, 5, pstep=3, width=8).double()
    nodes = torch.randn(7, 4, dtype=torch.float64)
    # chain 3 -> 2 -> 1 -> 0, 4 -> 0; node 5 only receives, node 6 has no relation
    receivers, senders = torch.tensor([2, 1, 0, 0, 5]), torch.tensor([3, 2, 1, 4, 0])
    relations = torch.randn(5, 5, dtype=torch.float64)
    dense = _dense_effects(net, nodes, relations, receivers, senders)
    tight = {"rtol": 1e-12, "atol": 1e-12}
    torch.testing.assert_close(net.effects(nodes, relations, receivers, senders, torch.arange(7)), dense, **tight)
    out = torch.tensor([0, 2])
    assert dense[out].abs().sum() > 0
    pred = net(nodes, relations, receivers, senders, out)
    torch.testing.assert_close(pred, net.predictor(dense[out]), **tight)
    # a new node 7 that sends nothing (it receives from node 0) leaves every other node as it was
    more = (torch.cat([nodes, torch.randn(1, 4, dtype=torch.float64)]), torch.cat([relations, torch.randn(1, 5).double()]),
            torch.cat([receivers, torch.tensor([7])]), torch.cat([senders, torch.tensor([0])]))
    torch.testing.assert_close(net(*more, out), pred, **tight)
    torch.testing.assert_close(_dense_effects(net, *more)[:7], dense, **tight)


@pytest.mark.parametrize("name", list(BASELINES))
def test_predictions_loss_and_grads_match_the_dense_reference(store_path, name, monkeypatch):
    """The pruned, split PropNet and the posing of used samples only change nothing but float rounding."""
    model = _model(name, **({} if name == "adaptigraph" else WIDE)).eval()
    layout, a = _window(store_path, "ep_000000", model.history + model.sequence)

    def run():
        model.zero_grad()
        x, _ = model.rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
        loss = model.window_loss(layout, a["x"], a["poses"])
        loss.backward()
        return x - a["x"][:, :1], loss.detach(), [p.grad.clone() for p in model.parameters()]

    got = run()
    monkeypatch.setattr(model.net, "effects", lambda nodes, rel, rr, ss, outputs:
                        _dense_effects(model.net, nodes, rel, rr, ss)[outputs])
    monkeypatch.setattr(base, "sample_frames", _all_sample_frames)
    want = run()
    assert want[0].abs().max() > 1e-4  # the particles do move
    torch.testing.assert_close(got[0], want[0], rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(got[1], want[1], rtol=1e-6, atol=0.0)
    for g, w in zip(got[2], want[2]):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-5 * float(w.abs().max()))


@pytest.mark.parametrize("name", list(BASELINES))
def test_rollout_gives_every_vertex_and_finite_difference_velocity(store_path, name):
    layout, a = _window(store_path, "ep_000001", 5)
    model = _model(name).eval()
    x, v = model.rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
    n = layout.num_vertices
    assert x.shape == v.shape == (1, 4, n, 3) and torch.isfinite(x).all()
    prev = torch.cat([a["x"][:, :1], x[:, :-1]], 1)
    torch.testing.assert_close(v, (x - prev) / 0.04)
    with pytest.raises(ValueError, match="poses must be"):
        model.rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"][:, :1], 0.04)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(BASELINES))
def test_one_training_step_lowers_the_loss_on_a_fixed_batch(store_path, name):
    model = _model(name, **({} if name == "adaptigraph" else WIDE))
    layout, a = _window(store_path, "ep_000000", model.history + model.sequence)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    before = model.window_loss(layout, a["x"], a["poses"])
    optimizer.zero_grad()
    before.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
    optimizer.step()
    after = model.window_loss(layout, a["x"], a["poses"]).detach()
    assert float(after) < float(before.detach())


@pytest.mark.slow
def test_contact_gating_keeps_untouched_objects_still(store_path):
    """RoboCraft without a tool in contact and RoboCook without a tool relation predict no motion."""
    for name in ("robocraft", "robocook"):
        model = _model(name, tool_radius_m=1e-4, neighbor_radius_m=0.05).eval()
        layout, a = _window(store_path, "ep_000000", 6)
        x, _ = model.rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
        torch.testing.assert_close(x, a["x"][:, :1].expand_as(x))


def test_map_back_is_exact_at_particles_and_follows_rigid_translation(store_path):
    layout, a = _window(store_path, "ep_000000", 2)
    pmap = particle_map(layout, 20)
    assert pmap.vertices.unique().numel() == 20
    torch.testing.assert_close(pmap.weights.sum(1), torch.ones(layout.num_vertices))
    x0 = a["x"][:, 0]
    p0 = x0[:, pmap.vertices]
    p = p0[:, None] + torch.randn(1, 3, 20, 3) * 0.01
    x = pmap.to_vertices(x0, p0, p)
    assert torch.equal(x[:, :, pmap.vertices], p)
    shift = torch.tensor([0.01, -0.02, 0.03])
    torch.testing.assert_close(pmap.to_vertices(x0, p0, (p0 + shift)[:, None]), (x0 + shift)[:, None])
    assert particle_map(layout, 20) is pmap  # cached per layout
    everything = particle_map(layout, 10_000)
    assert everything.vertices.numel() == layout.num_vertices


def test_set_losses():
    a = torch.randn(2, 8, 3)
    perm = a[:, torch.randperm(8)]
    assert float(emd(a, perm)) < 1e-6 and float(chamfer(a, perm)) < 1e-6
    shift = torch.tensor([0.3, 0.0, 0.4])
    assert abs(float(emd(a, a + shift)) - 0.5) < 1e-5  # a rigid shift is its own optimal matching
    b = torch.zeros(1, 4, 3)
    c = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]]])
    assert float(emd(b, c)) == pytest.approx(1.5) and float(chamfer(b, c)) == pytest.approx(1.5)
    with pytest.raises(ValueError, match="must both be"):
        emd(a, a[:, :4])


@pytest.mark.parametrize("name", list(BASELINES))
def test_save_load_gives_identical_predictions(store_path, tmp_path, name):
    layout, a = _window(store_path, "ep_000001", 4)
    model = _model(name).eval()
    save_baseline(model, tmp_path / name, {"note": "test"})
    loaded = load_baseline(tmp_path / name)
    assert type(loaded) is type(model) and loaded.params == model.params
    want = model.rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
    got = loaded.rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"], 0.04)
    assert torch.equal(want[0], got[0]) and torch.equal(want[1], got[1])


def test_missing_or_corrupt_baseline(tmp_path):
    with pytest.raises(FileNotFoundError, match="model.safetensors"):
        load_baseline(tmp_path)
    save_baseline(_model("robocook"), tmp_path / "m", {})
    (tmp_path / "m" / "model.safetensors").write_bytes(b"junk")
    with pytest.raises(ValueError, match="unreadable"):
        load_baseline(tmp_path / "m")
    with pytest.raises(ValueError, match="unknown baseline"):
        build_baseline("dpi", BaselineParams(**TINY["models"]["robocook"]))


@pytest.mark.slow
def test_stage_trains_every_baseline_and_reports(store_path, params, tmp_path):
    report = run(params, store_path, tmp_path / "models", tmp_path / "report.json")
    saved = json.loads((tmp_path / "report.json").read_text())
    assert set(saved["baselines"]) == set(BASELINES)
    for name, r in report["baselines"].items():
        assert np.isfinite(r["final_train_loss"]) and np.isfinite(r["rollout_position_mse_m2"])
        assert r["s_per_step_median"] > 0 and len(r["history"]) == 1
        model = load_baseline(tmp_path / "models" / name)
        assert model.name == name
        assert not (tmp_path / "models" / f"{name}.partial").exists()


def test_bad_params_are_named(params, store_path, tmp_path):
    bad = copy.deepcopy(params)
    bad["baselines"]["names"] = ["robocraft", "gns"]
    bad["baselines"]["models"]["gns"] = dict(TINY["models"]["robocook"])
    with pytest.raises(ParamsError, match="gns"):
        run(bad, store_path, tmp_path / "m", tmp_path / "r.json")
    bad = copy.deepcopy(params)
    bad["baselines"]["models"]["robocook"]["neighbor_radius_m"] = 0.0
    with pytest.raises(ParamsError, match="neighbor_radius_m"):
        run(bad, store_path, tmp_path / "m", tmp_path / "r.json")
    bad = copy.deepcopy(params)
    del bad["baselines"]["models"]["adaptigraph"]
    with pytest.raises(ParamsError, match="models.adaptigraph"):
        run(bad, store_path, tmp_path / "m", tmp_path / "r.json")


def test_stop_rule_converges_after_patience_and_restores_the_best_weights():
    model = torch.nn.Linear(2, 1)
    rule = StopRule(patience_evals=2)
    rule.record(10, 1.0, model)
    best = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        model.weight.add_(1.0)
    rule.record(20, 1.5, model)
    assert not rule.converged()
    rule.record(30, 1.2, model)
    assert rule.converged() and rule.best_step == 10 and rule.reason(30, 100) == "converged"
    rule.restore_best(model)
    assert all(torch.equal(model.state_dict()[k], v) for k, v in best.items())
    assert not StopRule().converged() and not StopRule().out_of_time()
    assert StopRule().reason(100, 100) == "steps" and StopRule().reason(40, 100) == "time"


def test_time_budget_stops_training_after_the_step_that_passes_it(params, store_path, tmp_path):
    cfg = load_section({**params, "baselines": {**copy.deepcopy(TINY), "max_minutes": 1e-9}}, "baselines",
                       BaselinesConfig)
    cfg = dataclasses.replace(cfg, models={**cfg.models, "robocook": dataclasses.replace(cfg.models["robocook"],
                                                                                            steps=50)})
    report = train_baseline("robocook", store_path, tmp_path / "robocook", cfg, load_section(params, "train", TrainConfig))
    assert report["steps_done"] == 1 and report["stopped_by"] == "time"
    assert [h["step"] for h in report["history"]] == [1] and report["best_step"] == 1
    assert load_baseline(tmp_path / "robocook").name == "robocook"


def test_budget_params_are_checked(params):
    for key in ("max_minutes", "patience_evals"):
        with pytest.raises(ParamsError, match=key):
            load_section({**params, "baselines": {**copy.deepcopy(TINY), key: -1}}, "baselines", BaselinesConfig)
