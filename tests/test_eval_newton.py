"""The Newton source simulator as an evaluated method: replay of a freshly simulated tiny episode, cheaper settings,
the coarse-resolution state maps, the params checks and its rows on the speed-accuracy chart."""

from __future__ import annotations

import copy
import csv
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from tests.conftest import load_params
from wc.config import ParamsError, load_section
from wc.data.store import TrajectoryStore, TrajectoryWriter
from wc.dynamics import Dynamics, ObjectState
from wc.eval.cases import CaseReader
from wc.eval.config import EvaluateConfig, MethodSpec
from wc.eval.methods import LearnedMethod, predict
from wc.eval.newton_method import NewtonMethod, coarse_scene_config
from wc.eval.predictors import ZeroMotion
from wc.eval.stage import evaluate, held_out_scores
from wc.scene.config import SceneConfig
from wc.scene.resample import ResolutionMap, surface_map
from wc.scene.scene import build_scene
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator
from wc.train.data import Phase, episode_phases

FRAMES = 7
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    """params.yaml at a tiny size: a 200-vertex bag, 10 solver steps per 0.04 s frame."""
    p = load_params()
    p["scene"]["bag"]["target_vertices"] = 200
    p["sim"].update(substeps=10, dt_s=0.004, iterations=4)
    return p


@pytest.fixture(scope="module")
def configs(params) -> tuple[SceneConfig, SimConfig]:
    return load_section(params, "scene", SceneConfig), load_section(params, "sim", SimConfig)


@pytest.fixture(scope="module")
def store_path(tmp_path_factory, configs) -> Path:
    """One test episode simulated by Newton: the bag dropped 3 cm onto the table, the robot at home."""
    scene_cfg, sim_cfg = configs
    scene = build_scene(scene_cfg, ["bag"])
    x0 = scene.objects["bag"].vertices + np.float32([0.0, 0.0, 0.03])
    action = np.repeat(scene.home_action()[None], FRAMES, axis=0)
    x, v = NewtonSimulator(scene, sim_cfg).rollout(ObjectState(x0, np.zeros_like(x0)), action)
    path = tmp_path_factory.mktemp("newton") / "drop.zarr"
    with TrajectoryWriter(path, dt=sim_cfg.frame_dt_s, substeps=sim_cfg.substeps, params_hash="test",
                          created_by="tests", object_order=["bag"], link_names=list(scene.link_names),
                          env_names=list(scene.env_names), chunk_frames=8) as w:
        w.add_scene(scene)
        w.add_episode(x, v, action, scene.link_poses(action), np.repeat(scene.env_poses()[None], FRAMES, axis=0),
                      episode_id="ep_000000", task="bag_drop", seed=0, cell=0, speed=0.0, amplitude=0.0,
                      split="test", accepted=True, first_failure=None, source="simulator")
    return path


def _case(store_path: Path, scene_cfg: SceneConfig, start: int = 0):
    store = TrajectoryStore(store_path)
    phase = episode_phases(store, "ep_000000")[0]
    return store, CaseReader(store, scene_cfg, 0.02, CPU).case(Phase(phase.episode, start, phase.stop, phase.layout),
                                                               FRAMES)


def _timed(method: NewtonMethod, case, dt: float) -> tuple[np.ndarray, float]:
    """Positions (S, N, 3) and the fastest of two timed rollouts, s per step (after the untimed build)."""
    dynamics = method.dynamics(case, dt)
    best, x = float("inf"), None
    for _ in range(2):
        t0 = time.perf_counter()
        x, _ = predict(dynamics, case)
        best = min(best, (time.perf_counter() - t0) / case.steps)
    return x, best


def _mse(x: np.ndarray, truth: np.ndarray) -> float:
    return float(np.square(x - truth).sum(-1).mean())


@pytest.mark.slow
def test_reference_replay_reproduces_and_a_coarser_setting_is_faster_and_worse(store_path, configs):
    scene_cfg, sim_cfg = configs
    store, case = _case(store_path, scene_cfg)
    truth = case.x[1:].astype(np.float64)
    ref_x, ref_s = _timed(NewtonMethod(MethodSpec("newton"), scene_cfg, sim_cfg, CPU), case, store.dt)
    assert ref_x.shape == truth.shape
    assert _mse(ref_x, truth) < 1e-10  # same simulator, same state, same actions: its own determinism only
    cheap_x, cheap_s = _timed(NewtonMethod(MethodSpec("newton", substeps=2), scene_cfg, sim_cfg, CPU), case, store.dt)
    assert np.isfinite(cheap_x).all()
    assert cheap_s < ref_s  # 2 instead of 10 solver steps per frame
    fallen = _mse(case.x[:1].astype(np.float64).repeat(case.steps, 0), truth)
    assert 1e-10 < _mse(cheap_x, truth) < fallen  # a different answer, still a falling bag

    # replayed from a later stored frame (the solver's history lost) it stays within 1 mm RMS
    store, late = _case(store_path, scene_cfg, start=2)
    x, _ = predict(NewtonMethod(MethodSpec("newton"), scene_cfg, sim_cfg, CPU).dynamics(late, store.dt), late)
    assert _mse(x, late.x[1:]) < 1e-6


@pytest.mark.slow
def test_half_resolution_runs_on_the_coarse_mesh_and_answers_in_the_stored_vertices(store_path, configs):
    scene_cfg, sim_cfg = configs
    store, case = _case(store_path, scene_cfg)
    method = NewtonMethod(MethodSpec("newton", cloth_vertices_scale=0.5), scene_cfg, sim_cfg, CPU)
    x, v = predict(method.dynamics(case, store.dt), case)
    (replay,) = method._replays.values()
    assert replay.sim.scene.num_vertices < 0.6 * case.scene.num_vertices
    assert x.shape == v.shape == case.x[1:].shape and np.isfinite(x).all()
    assert 0 < _mse(x, case.x[1:]) < _mse(case.x[:1].repeat(case.steps, 0), case.x[1:])


@pytest.mark.slow
@pytest.mark.parametrize("scale", [None, 0.5], ids=["reference", "half_resolution"])
def test_stepping_newton_gives_the_rollouts_frames(store_path, configs, scale):
    """NewtonSimulator.step (through the evaluated Replay, on the stored mesh and on a coarse one) goes on with the
    solver's history: frame by frame it gives rollout's frames; from another state it starts afresh there."""
    scene_cfg, sim_cfg = configs
    store, case = _case(store_path, scene_cfg)
    method = NewtonMethod(MethodSpec("newton", cloth_vertices_scale=scale), scene_cfg, sim_cfg, CPU)
    dynamics = method.dynamics(case, store.dt)
    assert isinstance(dynamics, Dynamics) and isinstance(dynamics.sim, Dynamics)
    initial, actions = ObjectState(case.x[0], case.v[0]), case.actions
    x, v = dynamics.rollout(initial, actions)
    dynamics.start(initial, actions[0])
    states = [initial]
    for action in actions[1:]:
        states.append(dynamics.step(states[-1], action))
    np.testing.assert_allclose(np.stack([s.x for s in states]), x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.stack([s.v for s in states]), v, rtol=0, atol=1e-4)
    dynamics.start(initial, actions[0])
    dynamics.step(initial, actions[1])
    other = ObjectState(case.x[2], case.v[2])  # not the state the step gave (the recording's frame 1 would be it)
    np.testing.assert_allclose(dynamics.step(other, actions[2]).x, dynamics.rollout(other, actions[1:3])[0][1],
                               rtol=0, atol=1e-6)
    with pytest.raises(RuntimeError, match="before start"):  # a rollout in between ends the stepped episode
        dynamics.step(other, actions[2])


def test_resolution_map_round_trips_rest_positions(configs):
    scene_cfg, _ = configs
    fine = build_scene(scene_cfg, ["bag", "sphere"])
    coarse = build_scene(coarse_scene_config(scene_cfg, fine, 0.5), ["bag", "sphere"])
    bag, small = fine.objects["bag"], coarse.objects["bag"]
    assert len(small.vertices) < len(bag.vertices)
    identity = surface_map(bag.vertices, bag.faces, bag.vertices)  # a mesh onto its own vertices
    np.testing.assert_allclose(identity.apply(bag.vertices), bag.vertices, atol=1e-12)
    m = ResolutionMap(fine, coarse)
    rest_fine = np.concatenate([o.vertices for o in fine.objects.values()]).astype(np.float64)
    rest_coarse = np.concatenate([o.vertices for o in coarse.objects.values()]).astype(np.float64)
    up = m.to_fine(rest_coarse)
    # fine vertices on the coarse surface (the flat bottom, z = 0) come back exactly; the rest within a chord
    bottom = np.flatnonzero(np.abs(rest_fine[: len(bag.vertices), 2]) < 1e-7)
    assert len(bottom) > 10
    np.testing.assert_allclose(up[bottom], rest_fine[bottom], atol=1e-7)
    assert np.abs(up - rest_fine).max() < 0.01
    rigid = fine.vertex_slices()["sphere"]
    np.testing.assert_array_equal(up[rigid], rest_fine[rigid])  # rigid objects are copied
    # linear: an affine motion of the rest shape maps to the same motion of the mapped points
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(m.to_fine(rest_coarse @ rot.T + 0.1), up @ rot.T + 0.1, atol=1e-12)
    np.testing.assert_allclose(m.to_coarse(rest_fine)[coarse.vertex_slices()["bag"]],
                               rest_coarse[coarse.vertex_slices()["bag"]], atol=0.01)
    with pytest.raises(ValueError, match="state"):
        m.to_fine(rest_fine)


@pytest.mark.parametrize("entry, key", [
    ({"kind": "newton", "iterations": 0}, "iterations"),
    ({"kind": "newton", "substeps": 0}, "substeps"),
    ({"kind": "newton", "cloth_vertices_scale": 0.0}, "cloth_vertices_scale"),
    ({"kind": "zero_motion", "substeps": 5}, "substeps"),
    ({"kind": "newton", "path": "models/x"}, "path"),
    ({"kind": "newton", "dt_s": 0.001}, "dt_s"),
])
def test_bad_newton_method_params_are_named(params, entry, key):
    p = copy.deepcopy(params)
    p["evaluate"]["methods"] = {"sim_bad": entry}
    with pytest.raises(ParamsError, match=rf"evaluate\.methods\.sim_bad.*{key}"):
        load_section(p, "evaluate", EvaluateConfig)


def test_bad_chart_max_cases_is_named(params):
    p = copy.deepcopy(params)
    p["evaluate"]["chart_max_cases"] = 0
    with pytest.raises(ParamsError, match="chart_max_cases"):
        load_section(p, "evaluate", EvaluateConfig)


@pytest.mark.slow
def test_stage_puts_newton_settings_on_the_chart_only(tmp_path, store_path, params):
    p = copy.deepcopy(params)
    p["evaluate"].update(rollout_frames=4, stability_frames=4, chart_max_cases=1, methods={
        "zero_motion": {"kind": "zero_motion"},
        "newton_reference": {"kind": "newton"},
        "newton_iterations_1": {"kind": "newton", "iterations": 1},
    })
    out = tmp_path / "reports"
    r = evaluate(p, store_path, out / "metrics.json", out / "stability.csv", out / "stability.png")
    assert set(r["methods"]) == {"zero_motion"}  # every held-out rollout: Newton is not there
    chart = r["speed_accuracy"]
    assert chart["rollouts"] == 1 and set(chart["methods"]) == {"zero_motion", "newton_reference", "newton_iterations_1"}
    assert chart["newton"]["newton_iterations_1"]["iterations"] == 1
    assert chart["newton"]["newton_reference"] == {"iterations": 4, "substeps": 10, "dt_s": pytest.approx(0.004),
                                                   "cloth_vertices_scale": 1.0}
    rows = {row["method"]: row for row in csv.DictReader((out / "speed_accuracy.csv").open())}
    assert set(rows) == set(chart["methods"]) and rows["newton_reference"]["kind"] == "newton"
    assert float(rows["newton_reference"]["position_mse_m2"]) < 1e-10 < float(rows["zero_motion"]["position_mse_m2"])
    for name, row in rows.items():
        assert float(row["simulated_s_per_wall_s"]) == pytest.approx(0.04 / chart["methods"][name]["s_per_step"])
    assert {row["method"] for row in csv.DictReader((out / "stability.csv").open())} == {"ground_truth", "zero_motion"}
    assert (out / "speed_accuracy.png").stat().st_size > 10_000


class CountingZeroMotion(ZeroMotion):
    """Zero motion that counts its rollouts."""

    def __init__(self) -> None:
        self.rollouts = 0

    def rollout(self, *args):  # noqa: ANN002, ANN201 - ZeroMotion.rollout's signature
        self.rollouts += 1
        return super().rollout(*args)


def test_every_method_rolls_the_first_chart_case_once_untimed(store_path, configs):
    """A learned method's first rollout compiles / captures its CUDA graph: the chart must not time it."""
    scene_cfg, _ = configs
    store = TrajectoryStore(store_path)
    phase = episode_phases(store, "ep_000000")[0]
    phases = [Phase(phase.episode, start, phase.stop, phase.layout) for start in (0, 2)]
    cfg = EvaluateConfig(rollout_frames=3, stability_frames=3, methods={"z": MethodSpec("zero_motion")},
                         chart_max_cases=1, episode_frames=3, phase_starts=0)  # one whole rollout per span
    counting = CountingZeroMotion()
    out = held_out_scores(CaseReader(store, scene_cfg, 0.02, CPU), phases, {"z": LearnedMethod(counting, CPU)}, cfg,
                          store.dt)
    assert len(out.rolled) == 2 and len(out.charted) == 1
    assert counting.rollouts == 3  # the charted rollout twice (warm-up + timed), the other once
    assert out.chart["z"].steps == out.charted[0]["steps"]  # the warm-up is neither timed nor scored


def test_a_phase_start_at_a_spans_first_frame_reuses_its_whole_rollout(store_path, configs):
    """The synthetic episodes have one motion phase: its start is the span's first frame, scored on the head of the
    whole rollout (planted bug caught: rolling it out again doubles the rollouts and their cost)."""
    scene_cfg, _ = configs
    store = TrajectoryStore(store_path)
    phase = episode_phases(store, "ep_000000")[0]
    cfg = EvaluateConfig(rollout_frames=2, stability_frames=3, methods={"z": MethodSpec("zero_motion")},
                         episode_frames=4, phase_starts=1)
    counting = CountingZeroMotion()
    out = held_out_scores(CaseReader(store, scene_cfg, 0.02, CPU), [phase], {"z": LearnedMethod(counting, CPU)}, cfg,
                          store.dt)
    assert [(r["label"], r["start_frame"], r["steps"]) for r in out.rolled] == [("episode", 0, 4), ("approach", 0, 2)]
    assert counting.rollouts == 3  # the whole rollout and the chart's 2-step one (warm-up, timed); not the phase start
    head = out.scores["z"].episode_errors.summary()["per_horizon"]["position_mse_m2"]  # the whole rollout, by step
    approach = out.scores["z"].summary()["per_phase"]["approach"]["position_mse_m2"]
    assert approach == pytest.approx((head["1"] + head["2"]) / 2, rel=1e-9) and head["2"] > 0
