"""A particle baseline's rollout starts with the information WorldContact gets: the history before frame 0 is the
recorded frames before it where there are any (what training windows hold), else frame 0 moved back at v0 - not a
bag at rest - and evaluate hands a case's recorded frames to it (wc.eval.cases, wc.model.learned_dynamics)."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from tests.conftest import load_params
from wc.baselines import BASELINES, build_baseline
from wc.baselines.base import ParticleDynamics, start_history
from wc.baselines.config import BaselineParams
from wc.baselines.train import recorded_past
from wc.data.store import TrajectoryStore
from wc.dynamics import ObjectState
from wc.eval.cases import CaseReader
from wc.eval.methods import LearnedMethod, predict
from wc.model.layout import scene_layout
from wc.model.past_frames import PastFrames
from wc.scene.config import SceneConfig
from wc.config import load_section
from wc.train.data import Phase, episode_phases, read_phase_window

DT = 0.04
PARTICLES = {"particles": 12, "steps": 1, "lr": 1e-4, "batch": 1, "neighbor_radius_m": 0.08, "tool_radius_m": 0.05,
             "max_step_m": 0.025, "tool_points_per_body": 2}
WIDE = {"tool_radius_m": 2.0, "max_step_m": 1.0}  # every tool point touches the bag: RoboCraft's non-rigid head


class ContinuesMotion(ParticleDynamics):
    """The simplest model of past frames: each particle repeats its last displacement (what a baseline that learned
    inertia does); everything else - history, unroll, map back to vertices - is the real baseline pipeline."""

    name = "continues_motion"
    sequence = 1

    def predict(self, step, graph):  # noqa: ANN001, ANN201 - ParticleDynamics.predict's signature
        return 2 * step.objects[:, -1] - step.objects[:, -2], graph


@pytest.fixture(scope="module")
def params() -> dict[str, Any]:
    return copy.deepcopy(load_params())


@pytest.fixture(scope="module")
def store_path(synthetic_store, params) -> Path:
    return synthetic_store(params, [("carry", "test"), ("handoff", "test")], frames=12)


def _window(store_path: Path, start: int, length: int):
    store = TrajectoryStore(store_path)
    phase = episode_phases(store, "ep_000000")[0]
    layout = scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), 1.0)
    a = {k: torch.from_numpy(v)[None] for k, v in read_phase_window(store, phase, start, length).items()}
    return layout, a


def _model(cls: type[ParticleDynamics] | str, **overrides: Any) -> ParticleDynamics:
    torch.manual_seed(0)
    params = BaselineParams(**{**PARTICLES, **overrides})
    model = build_baseline(cls, params) if isinstance(cls, str) else cls(params)
    model.set_statistics(torch.tensor([0.0, 0.0, 0.05]), torch.tensor([0.05, 0.03, 0.04]), 0.004)
    return model.eval()


def _first_step(model: ParticleDynamics, monkeypatch) -> list:
    """The StepInputs `model.predict` is called with, kept as they come."""
    seen, predict_step = [], model.predict
    monkeypatch.setattr(model, "predict", lambda step, graph: (seen.append(step), predict_step(step, graph))[1])
    return seen


def test_history_before_frame_0_is_the_recorded_past_then_moved_back_at_its_velocity():
    x0, v0 = torch.rand(2, 5, 3), torch.rand(2, 5, 3)
    pose0 = torch.rand(2, 4, 7)
    xs, poses = start_history(x0, v0, pose0, DT, 3)  # no past: x_{-k} = x0 - k v0 dt, bodies held at frame 0
    assert xs.shape == (2, 4, 5, 3) and poses.shape == (2, 3, 4, 7)
    for k in range(4):
        torch.testing.assert_close(xs[:, 3 - k], x0 - k * DT * v0)
    torch.testing.assert_close(poses, pose0[:, None].expand(-1, 3, -1, -1))
    past = PastFrames(torch.rand(2, 2, 5, 3), torch.rand(2, 2, 5, 3), torch.rand(2, 2, 4, 7))
    xs, poses = start_history(x0, v0, pose0, DT, 3, past)  # two recorded frames, the third moved back from them
    torch.testing.assert_close(xs[:, 1:3], past.x)
    torch.testing.assert_close(xs[:, 0], past.x[:, 0] - DT * past.v[:, 0])
    torch.testing.assert_close(poses, torch.cat([past.poses[:, :1], past.poses], 1))
    long = PastFrames(torch.rand(2, 6, 5, 3), torch.rand(2, 6, 5, 3), torch.rand(2, 6, 4, 7))
    xs, poses = start_history(x0, v0, pose0, DT, 3, long)  # more than needed: the last three
    torch.testing.assert_close(xs[:, :3], long.x[:, 3:])
    torch.testing.assert_close(poses, long.poses[:, 3:])


def test_a_baseline_rolled_out_from_a_moving_state_starts_with_its_velocity(store_path):
    """Planted bug caught: history from frame 0 repeated (the old padding) leaves the bag at rest for step 1."""
    layout, a = _window(store_path, 0, 5)
    x0 = a["x"][:, 0]
    v0 = torch.tensor([0.2, -0.1, 0.3]).expand_as(x0).contiguous()  # a common velocity: the map back is exact
    x, v = _model(ContinuesMotion).rollout(layout, x0, v0, a["poses"], DT)
    torch.testing.assert_close(x[:, 0] - x0, DT * v0, rtol=0, atol=1e-6)
    torch.testing.assert_close(v[:, 0], v0, rtol=0, atol=1e-4)
    torch.testing.assert_close(x[:, 3] - x0, 4 * DT * v0, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", list(BASELINES))
def test_each_baseline_sees_v0_or_the_recorded_frames_in_its_first_step(store_path, name, monkeypatch):
    model = _model(name, **({} if name == "adaptigraph" else WIDE))
    layout, a = _window(store_path, 0, 8)
    idx = model.scene(layout).particles.vertices
    x0, v0 = a["x"][:, 4], torch.full_like(a["x"][:, 4], 0.25)
    seen = _first_step(model, monkeypatch)
    moving, _ = model.rollout(layout, x0, v0, a["poses"][:, 4:], DT)
    first = seen[0].objects  # (1, H, K, 3) frames -3..0
    for k in range(4):
        torch.testing.assert_close(first[:, 3 - k], x0[:, idx] - k * DT * v0[:, idx])
    seen.clear()
    past = PastFrames(a["x"][:, 1:4], a["v"][:, 1:4], a["poses"][:, 1:4])
    recorded, _ = model.rollout(layout, x0, v0, a["poses"][:, 4:], DT, past)
    torch.testing.assert_close(seen[0].objects, a["x"][:, 1:5, idx])  # frames s-3..s as recorded
    torch.testing.assert_close(seen[0].tools[:, :4], _tools(model, layout, a["poses"][:, 1:5]))
    if name != "robocook":  # RoboCook reads the tools' motion and positions only: its particles' past does not enter
        rest, _ = model.rollout(layout, x0, torch.zeros_like(v0), a["poses"][:, 4:], DT)
        assert (moving - rest).abs().max() > 1e-7  # v0 is an input of the model now


def _tools(model: ParticleDynamics, layout, poses: torch.Tensor) -> torch.Tensor:
    from wc.baselines.base import sample_frames  # noqa: PLC0415

    sc = model.scene(layout)
    return sample_frames(layout, poses, sc.tool_samples)[0]


def test_evaluate_gives_a_baseline_the_cases_recorded_frames_before_its_start(store_path, params, monkeypatch):
    """A case from frame 5 carries frames 2..4; the baseline's first step reads frames 2..5 as recorded, and a case
    from the phase's first frame has none (v0 then)."""
    store = TrajectoryStore(store_path)
    model = _model("robocraft")
    reader = CaseReader(store, load_section(params, "scene", SceneConfig), 0.02, torch.device("cpu"),
                        past_frames=model.history - 1)
    phase = episode_phases(store, "ep_000000")[0]
    case = reader.case(phase, 4, start=5)
    assert case.start == 5 and case.past_x.shape[0] == 3 and case.steps == 3
    seen = _first_step(model, monkeypatch)
    predict(LearnedMethod(model, torch.device("cpu")).dynamics(case, store.dt), case)
    idx = model.scene(case.layout).particles.vertices
    whole = read_phase_window(store, phase, 2, 4)["x"][:, idx.numpy()]
    np.testing.assert_allclose(seen[0].objects[0].numpy(), whole, atol=0)
    assert reader.case(phase, 4).past_x.shape[0] == 0 and reader.case(phase, 4, start=1).past_x.shape[0] == 1


def test_stepping_a_baseline_from_a_case_gives_its_rollout(store_path, params):
    """Stepping replays from the case's recorded start, so it reads the same recorded past as the rollout."""
    store = TrajectoryStore(store_path)
    reader = CaseReader(store, load_section(params, "scene", SceneConfig), 0.02, torch.device("cpu"), past_frames=3)
    case = reader.case(episode_phases(store, "ep_000000")[0], 5, start=6)
    dynamics = LearnedMethod(_model(ContinuesMotion), torch.device("cpu")).dynamics(case, store.dt)
    x, _ = predict(dynamics, case)
    state = ObjectState(case.x[0], case.v[0])
    dynamics.start(state, case.actions[0])
    for k in range(1, 5):
        state = dynamics.step(state, case.actions[k])
        np.testing.assert_allclose(state.x, x[k - 1], atol=1e-6)
    np.testing.assert_allclose(x[0] - case.x[0], case.x[0] - case.past_x[-1], atol=1e-6)  # the recorded motion goes on


def test_the_recorded_past_stays_in_the_episodes_layout_and_reaches_before_a_held_out_block(store_path, params):
    """A held-out block starts with the episode's frames before it; after a hand-off's release the past is the
    second layout's frames only (before it the ball was a held body, not predicted vertices)."""
    store = TrajectoryStore(store_path)
    reader = CaseReader(store, load_section(params, "scene", SceneConfig), 0.02, torch.device("cpu"), past_frames=3)
    whole = episode_phases(store, "ep_000000")[0]
    block = Phase(whole.episode, 6, 10, whole.layout)
    case = reader.case(block, 3)
    np.testing.assert_array_equal(case.past_x, read_phase_window(store, whole, 3, 3)["x"])
    before, after = episode_phases(store, "ep_000001")
    assert reader.case(after, 3).past_x.shape[0] == 0
    later = reader.case(after, 3, start=after.start + 2)
    np.testing.assert_array_equal(later.past_x, read_phase_window(store, after, after.start, 2)["x"])
    assert reader.case(before, 3, start=2).past_x.shape[0] == 2
    past = recorded_past(store, block, 3, torch.device("cpu"))  # training's held-out rollouts read the same frames
    np.testing.assert_array_equal(past.x[0].numpy(), case.past_x)
    assert recorded_past(store, after, 3, torch.device("cpu")) is None
