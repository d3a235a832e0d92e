"""Evaluation: hand-made metric cases with known answers, the reference predictors, WorldContact's stepwise
rollout, divergence on a planted blow-up, and the `evaluate` stage end to end on a synthetic store."""

from __future__ import annotations

import copy
import dataclasses
import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import trimesh

from wc.eval.stage import evaluate, evaluate_summary
from tests.conftest import load_params
from tests.synthetic_store import write_synthetic_store
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore
from wc.model_ref import file_sha256
from wc.eval import (ConstantVelocity, ErrorTally, EvaluateConfig, PenetrationTally, WorldContactPredictor, ZeroMotion,
                     cloth_signed_distance, first_divergence, max_edge_strain, mesh_signed_distance,
                     penetrating_area_pct, squared_error)
from wc.baselines import build_baseline, save_baseline
from wc.baselines.config import BaselinesConfig
from wc.dynamics import Dynamics, ObjectState
from wc.eval.cases import CaseReader, held_out_phases
from wc.eval.map_back import MapBackTally, mapped_back
from wc.eval.config import MethodSpec
from wc.eval.methods import LearnedMethod
from wc.eval.newton_method import NewtonMethod, Replay
from wc.eval.predictors import load_predictor
from wc.eval.stage import load_methods
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.model.config import ModelConfig
from wc.model.layout import scene_layout
from wc.model.rollout import rollout
from wc.model.worldcontact import WorldContact
from wc.scene.scene import build_scene
from wc.train.checkpoint import save_weights
from wc.train.config import TrainConfig
from wc.train.data import episode_phases, read_phase_window
from wc.rotations import quat_matrices
from wc.validate.predicates import convex_depth, convex_planes, robot_boxes

DT = 0.04


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    return load_params()


@pytest.fixture(scope="module")
def scene(scene_cfg):
    return build_scene(scene_cfg, ["bag", "sphere"])


# -- penetration ----------------------------------------------------------------------------------------------

def test_penetration_counts_deep_cloth_by_area(scene):
    """2 cm inside the table counts, 0.5 cm does not (but is contact); a robot box and a rigid object count."""
    n = len(scene.objects["bag"].vertices)
    link_poses = scene.link_poses(scene.home_action()[None])
    link1 = robot_boxes(scene, link_poses)[0][0, 0]  # left link1 box centre (half extents 4.5 cm in x, y)
    centre = np.array([0.15, 0.1, 0.1])
    bag = np.tile([0.0, 0.0, 0.1], (n, 1))  # 10 cm above the table, far from everything
    bag[0] = (0.0, 0.0, -0.02)  # 2 cm inside the table
    bag[1] = (0.05, 0.0, -0.005)  # 0.5 cm inside
    bag[2] = (0.1, 0.0, 0.008)  # above the table, inside the 1 cm contact band
    bag[3] = centre  # at the sphere's centre
    bag[4] = link1
    sphere = scene.objects["sphere"].vertices + centre
    x = np.concatenate([bag, sphere])[None]
    sd = cloth_signed_distance(scene, x, link_poses, reach_m=0.01)
    assert sd.shape == (1, n)
    assert sd[0, :3] == pytest.approx([-0.02, -0.005, 0.008], abs=1e-6)
    assert -0.025 <= sd[0, 3] < -0.02  # the inscribed radius of the 2.5 cm polyhedral sphere
    assert sd[0, 4] == pytest.approx(-0.045, abs=1e-6)
    assert (sd[0, 5:] > 0.05).all()
    area = np.ones(n)
    area[[0, 1, 2, 3, 4]] = (3.0, 5.0, 7.0, 2.0, 1.0)
    tally = PenetrationTally(depth_m=0.01, band_m=0.01)
    tally.add(sd, area)
    assert tally.rate_pct == pytest.approx(100.0 * 6.0 / area.sum())
    assert tally.contact_rate_pct == pytest.approx(100.0 * 6.0 / 18.0)
    tally.add(np.full((1, n), 0.5), area)  # a second frame without contact halves the area rate only
    assert tally.rate_pct == pytest.approx(100.0 * 6.0 / (2 * area.sum()))
    assert tally.contact_rate_pct == pytest.approx(100.0 * 6.0 / 18.0)
    assert penetrating_area_pct(sd, area, 0.01) == pytest.approx([100.0 * 6.0 / area.sum()])
    assert penetrating_area_pct(sd, np.ones(n), 0.01) == pytest.approx([300.0 / n])  # areas, not counts


def test_mesh_signed_distance_is_exact_and_posed(scene):
    mesh = scene.objects["sphere"]
    rng = np.random.default_rng(0)
    rot = quat_matrices(np.array([0.0, 0.0, np.sin(0.4), np.cos(0.4)]))
    pos = np.array([0.1, -0.2, 0.3])
    direction = rng.normal(size=(40, 3))
    local = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0.0, 0.02, (40, 1))
    world = local @ rot.T + pos
    sd = mesh_signed_distance(world[:, None], mesh.vertices, mesh.faces, np.tile(pos, (40, 1)),
                              np.tile(rot, (40, 1, 1)), reach_m=0.01)[:, 0]
    depth = convex_depth(world[:, None], np.tile(pos, (40, 1)), np.tile(rot, (40, 1, 1)),
                         convex_planes(mesh.vertices, mesh.faces))
    assert sd == pytest.approx(-depth, abs=1e-6)  # inside a convex mesh: the nearest face plane
    out_local = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0.026, 0.03, (40, 1))
    got = mesh_signed_distance((out_local @ rot.T + pos)[:, None], mesh.vertices, mesh.faces, np.tile(pos, (40, 1)),
                               np.tile(rot, (40, 1, 1)), reach_m=0.01)[:, 0]
    tri = mesh.vertices[mesh.faces].astype(np.float64)  # brute force over every face, in the rest frame
    closest = trimesh.triangles.closest_point(np.tile(tri, (40, 1, 1)), np.repeat(out_local, len(tri), axis=0))
    want = np.linalg.norm(closest - np.repeat(out_local, len(tri), axis=0), axis=1).reshape(40, -1).min(axis=1)
    assert got == pytest.approx(want, abs=1e-6)


def test_non_finite_frames_have_no_geometry(scene):
    n = scene.num_vertices
    x = np.tile(np.concatenate([scene.objects["bag"].vertices, scene.objects["sphere"].vertices + 0.3]), (2, 1, 1))
    x[1, 7] = np.nan
    sd = cloth_signed_distance(scene, x, scene.link_poses(np.repeat(scene.home_action()[None], 2, 0)), 0.01)
    assert np.isfinite(sd[0]).all() and np.isnan(sd[1]).all() and x.shape[1] == n
    tally = PenetrationTally(0.01, 0.01)
    tally.add(sd, np.ones(sd.shape[1]))
    assert tally.frames == 1


# -- errors ---------------------------------------------------------------------------------------------------

def test_mse_of_identical_rollouts_is_zero_and_known_offsets_pool_by_vertex_frames():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4, 10, 3))
    assert squared_error(x, x) == pytest.approx(np.zeros(4))
    tally = ErrorTally(horizon=4)
    tally.add("a", x, x, x, x)
    assert tally.summary()["position_mse_m2"] == 0.0
    tally.add("b", x[:2, :5] + [0.01, 0.0, 0.0], x[:2, :5], x[:2, :5], x[:2, :5] + [0.0, 0.0, 0.2])
    s = tally.summary()
    assert s["position_mse_m2"] == pytest.approx(10 * 1e-4 / 50)  # 10 vertex-frames off by 1 cm of 50
    assert s["velocity_mse_m2_s2"] == pytest.approx(10 * 0.04 / 50)
    assert s["per_task"]["a"]["position_mse_m2"] == 0.0
    assert s["per_task"]["b"]["position_mse_m2"] == pytest.approx(1e-4)
    assert s["per_horizon"]["position_mse_m2"] == pytest.approx({"1": 5e-4 / 15, "2": 5e-4 / 15, "3": 0.0, "4": 0.0})
    tally.add("b", np.full((1, 10, 3), np.nan), x[:1], x[:1], x[:1])
    assert tally.summary()["position_mse_m2"] is None and tally.summary()["non_finite_rollouts"] == 1
    with pytest.raises(ValueError, match="exceeds"):
        tally.add("a", np.zeros((5, 1, 3)), np.zeros((5, 1, 3)), np.zeros((5, 1, 3)), np.zeros((5, 1, 3)))


def test_pareto_front_keeps_the_undominated_points():
    from wc.eval.plots import pareto_front
    points = [(10.0, 5.0), (1.0, 1.0), (5.0, 6.0), (100.0, 8.0), (1.0, 2.0)]
    assert pareto_front(points) == [3, 0, 1]  # fastest first; (5, 6) and (1, 2) are dominated


def test_reference_predictors():
    x0 = torch.randn(2, 6, 3)
    v0 = torch.randn(2, 6, 3)
    poses = torch.zeros(2, 4, 5, 7)
    x, v = ZeroMotion().rollout(None, x0, v0, poses, DT)
    assert x.shape == (2, 3, 6, 3) and torch.equal(x[:, 2], x0) and not v.any()
    x, v = ConstantVelocity().rollout(None, x0, v0, poses, DT)
    assert torch.allclose(x[:, 2], x0 + 3 * DT * v0) and torch.allclose(x[:, 0], x0 + DT * v0)
    assert torch.equal(v[:, 1], v0)
    with pytest.raises(ValueError, match="poses"):
        ZeroMotion().rollout(None, x0, v0, poses[:, :1], DT)


# -- stability ------------------------------------------------------------------------------------------------

def test_divergence_on_a_planted_blow_up():
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    edges = np.array([[0, 1], [1, 2], [2, 0]])
    lengths = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    x = np.repeat(rest[None], 10, axis=0)
    x[4:, 1, 0] = 3.5  # edge 0-1 stretched to 3.5x from step 5 (index 4)
    x[7:, 2] = np.nan
    strain = max_edge_strain(x, edges, lengths)
    assert strain[:4] == pytest.approx(np.zeros(4))
    assert strain[4] == pytest.approx(2.5)
    assert np.isnan(strain[7:]).all()
    finite = np.isfinite(x).all(axis=(1, 2))
    none = np.zeros(10)
    assert first_divergence(finite, strain, none, 2.0, 25.0) == 5
    assert first_divergence(finite, strain, none, 3.0, 25.0) == 8  # then the NaN
    penetration = np.where(np.arange(10) >= 2, 30.0, 0.0)
    assert first_divergence(finite, strain, penetration, 3.0, 25.0) == 3
    assert first_divergence(np.ones(10, bool), np.zeros(10), none, 2.0, 25.0) is None


# -- WorldContact and the stage -------------------------------------------------------------------------------

def _tiny_model(params) -> WorldContact:
    torch.manual_seed(0)
    model = WorldContact(load_section(params, "model", ModelConfig), velocity_m_s=0.3, delta_x_m=0.005,
                         delta_v_m_s=0.1).eval()
    torch.nn.init.normal_(model.head.mlp[-1].weight, std=0.1)  # visible predictions
    return model


@pytest.fixture(scope="module")
def store_path(synthetic_store, params) -> Path:
    episodes = [("fall", "train"), ("carry", "train"), ("fall", "test"), ("handoff", "test")]
    return synthetic_store(params, episodes, frames=10)


def test_worldcontact_predictor_matches_the_model_rollout(store_path, params):
    store = TrajectoryStore(store_path)
    phase = episode_phases(store, "ep_000001")[0]
    model = _tiny_model(params)
    layout = scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), model.config.tag_scale)
    a = {k: torch.from_numpy(v)[None] for k, v in read_phase_window(store, phase, 0, 4).items()}
    train_cfg = load_section(params, "train", TrainConfig)
    got = WorldContactPredictor(model, True, train_cfg).rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"], DT)
    with torch.no_grad():
        want = rollout(model, layout, a["x"][:, 0], a["v"][:, 0], a["poses"], DT,
                       model.projection(layout, train_cfg.smoothing_iterations, train_cfg.smoothing_weight,
                                        train_cfg.constraint_iterations, train_cfg.edge_ratio))
    assert torch.allclose(got[0], want[0], atol=1e-6) and torch.allclose(got[1], want[1], atol=1e-5)
    assert not torch.equal(got[0][:, 0], a["x"][:, 0])


def _stage_params(params: dict[str, Any], models: Path) -> dict[str, Any]:
    p = copy.deepcopy(params)
    p["evaluate"].update(rollout_frames=4, episode_frames=4, phase_starts=1, stability_frames=8, methods={
        "worldcontact": {"kind": "worldcontact", "path": str(models / "worldcontact")},
        "robocraft": {"kind": "baseline", "path": str(models / "baselines" / "robocraft")},
        "zero_motion": {"kind": "zero_motion"},
        "constant_velocity": {"kind": "constant_velocity"},
    })
    return p


def test_every_method_is_dynamics_of_a_case_and_steps_as_it_rolls_out(tmp_path, store_path, params):
    """Each kind evaluate loads is `Dynamics` over a case with its recorded inputs; the learned ones (WorldContact, a
    baseline with a 4-frame history, the references) give the same frames stepped one at a time as rolled out."""
    models = tmp_path / "models"
    (models / "worldcontact").mkdir(parents=True)
    save_weights(_tiny_model(params), models / "worldcontact" / "model.safetensors", {"projection": True})
    torch.manual_seed(0)
    baseline = build_baseline("robocraft", load_section(params, "baselines", BaselinesConfig).models["robocraft"])
    save_baseline(baseline, models / "baselines" / "robocraft", {})
    p = _stage_params(params, models)
    p["evaluate"]["methods"]["newton"] = {"kind": "newton", "substeps": 2}
    cfg, scene_cfg = load_section(p, "evaluate", EvaluateConfig), load_section(p, "scene", SceneConfig)
    methods, skipped = load_methods(cfg, load_section(p, "train", TrainConfig), 0.02, torch.device("cpu"), scene_cfg,
                                    load_section(p, "sim", SimConfig))
    assert set(methods) == set(cfg.methods) and not skipped
    assert isinstance(methods["newton"], NewtonMethod) and issubclass(Replay, Dynamics)  # built: test_eval_newton
    store = TrajectoryStore(store_path)
    reader = CaseReader(store, scene_cfg, 0.02, torch.device("cpu"))
    case = reader.case(episode_phases(store, "ep_000003")[0], 4)  # the hand-off's first phase: a held sphere
    initial = ObjectState(case.x[0], case.v[0])
    for name, method in methods.items():
        if name == "newton":
            continue
        assert isinstance(method, LearnedMethod)
        dynamics = method.dynamics(case, DT)
        assert isinstance(dynamics, Dynamics), name
        x, v = dynamics.rollout(initial, case.actions)
        dynamics.start(initial, case.actions[0])
        states = [initial]
        for action in case.actions[1:]:
            states.append(dynamics.step(states[-1], action))
        np.testing.assert_allclose(np.stack([s.x for s in states]), x, rtol=0, atol=1e-6, err_msg=name)
        np.testing.assert_allclose(np.stack([s.v for s in states]), v, rtol=0, atol=1e-4, err_msg=name)
        with pytest.raises(ValueError, match="not the recorded ones"):  # a case's recording answers its actions only
            dynamics.rollout(initial, case.actions + np.float32(0.01))


def test_the_map_back_floor_is_zero_at_every_vertex_and_pools_what_fewer_particles_miss(store_path, params):
    """A particle baseline's map-back floor: the recorded frames rebuilt from their own particles. Every vertex a
    particle: zero; 20 particles: the pooled MSE of the rebuilt frames against the recorded ones, by hand, above zero
    on a deforming bag."""
    store = TrajectoryStore(store_path)
    reader = CaseReader(store, load_section(params, "scene", SceneConfig), 0.02, torch.device("cpu"))
    case = reader.case(episode_phases(store, "ep_000003")[0], 4)  # the hand-off: a bag and a held sphere
    bent = np.random.default_rng(0).normal(0.0, 0.002, case.x.shape).astype(case.x.dtype)  # the synthetic motion
    bent[0] = 0.0  # is rigid, which any particle map rebuilds exactly: bend it from frame 1 on
    case = dataclasses.replace(case, x=case.x + bent)
    n = case.x.shape[1]
    base = load_section(params, "baselines", BaselinesConfig).models["robocraft"]
    tally = MapBackTally(4)
    for name, particles in (("every_vertex", 10_000), ("twenty", 20)):
        model = build_baseline("robocraft", dataclasses.replace(base, particles=particles))
        tally.add(name, LearnedMethod(model, torch.device("cpu")), case)
    tally.add("zero_motion", LearnedMethod(ZeroMotion(), torch.device("cpu")), case)  # no particles: no floor
    floor = tally.summary()
    assert set(floor) == {"every_vertex", "twenty"}
    assert floor["every_vertex"]["position_mse_m2"] == 0.0 and floor["every_vertex"]["layouts"] == [
        {"particles": n, "vertices": n}]
    pmap = build_baseline("robocraft", dataclasses.replace(base, particles=20)).scene(case.layout).particles
    x = case.x.astype(np.float64)
    rebuilt = mapped_back(pmap, x)
    np.testing.assert_array_equal(rebuilt[:, pmap.vertices.numpy()], x[1:, pmap.vertices.numpy()])  # exact there
    assert floor["twenty"]["position_mse_m2"] == pytest.approx(np.square(rebuilt - x[1:]).sum(-1).mean(), rel=1e-9)
    assert floor["twenty"]["position_mse_m2"] > 0 and floor["twenty"]["per_task"] == {
        case.task: floor["twenty"]["position_mse_m2"]}
    with pytest.raises(ValueError, match="vertices"):
        mapped_back(pmap, x[:, :-1])
    printed = evaluate_summary({"held_out": {"rollouts": 1, "source": "test split"}, "wall_s": 1.0, "methods": {},
                                "skipped": {}, "map_back": floor}).splitlines()
    assert any("twenty" in line and "map-back floor" in line and f"20 of {n} vertices" in line for line in printed)


@pytest.mark.slow
def test_evaluate_stage_end_to_end(tmp_path, store_path, params):
    models = tmp_path / "models"
    (models / "worldcontact").mkdir(parents=True)
    save_weights(_tiny_model(params), models / "worldcontact" / "model.safetensors", {"projection": True})
    out = tmp_path / "reports"
    r = evaluate(_stage_params(params, models), store_path, out / "metrics.json", out / "stability.csv",
                 out / "stability.png")
    assert json.loads((out / "metrics.json").read_text()) == json.loads(json.dumps(r))
    assert set(r["methods"]) == {"worldcontact", "zero_motion", "constant_velocity"}
    assert "robocraft" in r["skipped"] and "not found" in r["skipped"]["robocraft"]
    assert r["map_back"] == {}  # no particle baseline was evaluated
    assert r["held_out"]["source"] == "test split"
    assert r["kinds"] == {"worldcontact": "worldcontact", "zero_motion": "zero_motion",
                          "constant_velocity": "constant_velocity"}
    weights = models / "worldcontact" / "model.safetensors"  # the report names the weights by their hash
    assert set(r["models"]) == {"worldcontact"} and r["models"]["worldcontact"]["sha256"] == file_sha256(weights)
    assert r["dt"] == pytest.approx(TrajectoryStore(store_path).dt)
    whole = [h for h in r["held_out"]["phases"] if h["label"] == "episode"]
    assert len(whole) == 3  # the fall, and the hand-off's two phases, each from its first frame
    assert len(r["held_out"]["phases"]) == r["held_out"]["rollouts"] == 6  # and one from a motion phase of each
    # zero motion, by hand: pooled over every vertex-frame of the three whole rollouts
    store = TrajectoryStore(store_path)
    sums = count = 0.0
    for eid in ("ep_000002", "ep_000003"):
        for phase in episode_phases(store, eid):
            x = read_phase_window(store, phase, phase.start, min(5, phase.stop - phase.start))["x"].astype(np.float64)
            sums += np.square(x[1:] - x[:1]).sum()
            count += x[1:].shape[0] * x.shape[1]
    zero = r["methods"]["zero_motion"]
    assert zero["whole_episode"]["position_mse_m2"] == pytest.approx(sums / count, rel=1e-6)
    assert set(zero["per_phase"]) == {h["label"] for h in r["held_out"]["phases"]} - {"episode"}
    ratios = r["whole_episode"]  # WorldContact against the best of the references, task by task
    assert ratios["subject"] == "worldcontact" and ratios["baselines"] == ["zero_motion", "constant_velocity"]
    for task, row in ratios["per_task"].items():
        mse = {m: r["methods"][m]["whole_episode"]["per_task"][task]["position_mse_m2"] for m in ratios["baselines"]}
        assert row["best_baseline_mse_m2"] == min(mse.values())
        assert row["ratio"] == pytest.approx(min(mse.values()) / row["subject_mse_m2"])
    assert ratios["mean_task_ratio"] == pytest.approx(np.mean([row["ratio"] for row in ratios["per_task"].values()]))
    assert ratios["penetration_pct"] == r["methods"]["worldcontact"]["whole_episode"]["penetration_rate_pct"]
    assert set(zero["per_task"]) == {"fall", "handoff"}
    assert set(zero["per_horizon"]["position_mse_m2"]) == {"1", "2", "3", "4"}
    wc = r["methods"]["worldcontact"]
    assert wc["position_mse_m2"] > 0 and wc["penetration_rate_pct"] is not None and wc["s_per_step"] > 0
    assert r["ground_truth"]["penetration_rate_pct"] == 0.0
    rows = list(csv.DictReader((out / "stability.csv").open()))
    long_steps = {(row["method"], row["task"]) for row in rows}
    assert long_steps == {(m, t) for m in ("ground_truth", "worldcontact", "zero_motion", "constant_velocity")
                          for t in ("fall", "handoff")}
    assert max(int(row["step"]) for row in rows) == 8
    assert r["stability"]["methods"]["ground_truth"]["diverged"] == 0
    assert (out / "stability.png").stat().st_size > 10_000
    speed = {row["method"]: row for row in csv.DictReader((out / "speed_accuracy.csv").open())}
    assert set(speed) == set(r["methods"])
    for name, m in r["speed_accuracy"]["methods"].items():  # simulated s per wall s of its charted rollouts
        assert float(speed[name]["simulated_s_per_wall_s"]) == pytest.approx(store.dt / m["s_per_step"], rel=1e-6)
        assert float(speed[name]["position_mse_m2"]) == pytest.approx(m["position_mse_m2"], rel=1e-6)
    assert (out / "speed_accuracy.png").stat().st_size > 10_000


def test_held_out_data_falls_back_to_training_validation(tmp_path, params):
    path = write_synthetic_store(tmp_path / "t.zarr", params, [("fall", "train"), ("carry", "train")], frames=60)
    phases, source = held_out_phases(TrajectoryStore(path), load_section(params, "train", TrainConfig))
    assert phases and "no test split" in source
    assert all(p.stop - p.start < 60 for p in phases)  # part of each episode, not all of it


def test_bad_evaluate_params_are_named(params):
    p = copy.deepcopy(params)
    p["evaluate"]["methods"] = {"wc": {"kind": "worldcontact"}}
    with pytest.raises(ParamsError, match="evaluate.methods.wc"):
        load_section(p, "evaluate", EvaluateConfig)
    p = copy.deepcopy(params)
    p["evaluate"]["contact_band_m"] = 0.0
    with pytest.raises(ParamsError, match="contact_band_m"):
        load_section(p, "evaluate", EvaluateConfig)


def test_a_worldcontact_method_sets_its_own_precision(tmp_path, params):
    save_weights(_tiny_model(params), tmp_path / "wc" / "model.safetensors", {"projection": False})
    train_cfg = load_section(params, "train", TrainConfig)
    for key in ("autocast_bf16", "cuda_graph"):
        for flag in (True, False):
            spec = MethodSpec("worldcontact", str(tmp_path / "wc"), **{key: flag})
            assert getattr(load_predictor(spec, train_cfg, torch.device("cpu")).train_cfg, key) is flag
        unset = load_predictor(MethodSpec("worldcontact", str(tmp_path / "wc")), train_cfg, torch.device("cpu"))
        assert getattr(unset.train_cfg, key) is getattr(train_cfg, key)
        p = copy.deepcopy(params)
        p["evaluate"]["methods"] = {"cv": {"kind": "constant_velocity", key: True}}
        with pytest.raises(ParamsError, match=key):
            load_section(p, "evaluate", EvaluateConfig)


def test_a_stability_csv_reads_back_into_its_curves_and_figure(tmp_path):
    from wc.eval.replot import main as replot_main
    from wc.eval.stability import CSV_HEADER, StabilityCurve, csv_rows, read_csv_curves
    from wc.reports import write_csv_atomic

    curves = [StabilityCurve("worldcontact", "lift", "ep_000003", 0, np.array([1e-4, 2e-4, np.nan]),
                             np.array([0.0, 1.0, 2.0]), np.array([0.1, 2.5, np.nan]), 2),
              StabilityCurve("constant_velocity", "lift", "ep_000003", 0, np.array([3e-4, 5e-4]),
                             np.zeros(2), np.zeros(2), None)]
    path = write_csv_atomic(tmp_path / "stability.csv", CSV_HEADER, csv_rows(curves, 0.04))
    back, dt = read_csv_curves(path)
    assert dt == pytest.approx(0.04) and len(back) == 2
    for a, b in zip(curves, back):
        assert (a.method, a.task, a.episode, a.start_frame, a.divergence_step) == \
            (b.method, b.task, b.episode, b.start_frame, b.divergence_step)
        for field in ("position_mse_m2", "penetration_rate_pct", "max_edge_strain"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    replot_main([str(path), str(tmp_path / "again.png"), "--strain-bound", "2.0"])
    assert (tmp_path / "again.png").stat().st_size > 10_000
    (tmp_path / "other.csv").write_text("policy,successes\nx,1\n")
    with pytest.raises(ValueError, match="other.csv: not a stability CSV"):
        read_csv_curves(tmp_path / "other.csv")
