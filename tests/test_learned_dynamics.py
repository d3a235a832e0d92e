"""A learned predictor as `wc.dynamics.Dynamics` (wc.model.learned_dynamics): the Newton simulator's call - frame-0
object states and 14-D actions in, (x, v) per frame out - with the robot's poses from the scene's kinematics or as
recorded; stepping frame by frame gives the rollout's frames, for a model with history too."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from wc.dynamics import Dynamics, ObjectState
from wc.eval.predictors import ConstantVelocity
from wc.model.learned_dynamics import LearnedDynamics, finite_rollout
from wc.model.prescribed_inputs import KinematicInputs, RecordedInputs
from wc.scene.scene import build_scene
from wc.sim.newton_sim import NewtonSimulator

DT = 0.04


@pytest.fixture(scope="module")
def scene(scene_cfg):
    return build_scene(scene_cfg, ["bag"])


class PoseRecorder(ConstantVelocity):
    """Constant velocity that keeps the poses it was given."""

    def rollout(self, layout, x0, v0, poses, dt):  # noqa: ANN001, ANN201 - Predictor.rollout's signature
        self.poses = poses.clone()
        return super().rollout(layout, x0, v0, poses, dt)


class Accelerating(ConstantVelocity):
    """A model with history: x_k = x_0 + k^2 mm along z from the frame its history starts, whatever v is."""

    history = 3

    def rollout(self, layout, x0, v0, poses, dt):  # noqa: ANN001, ANN201 - Predictor.rollout's signature
        k = torch.arange(1, poses.shape[1], dtype=x0.dtype)[None, :, None, None]
        x = x0[:, None] + 1e-3 * k ** 2 * torch.tensor([0.0, 0.0, 1.0])
        return x, torch.zeros_like(x)


class Diverging(ConstantVelocity):
    """Blows up at once."""

    def rollout(self, layout, x0, v0, poses, dt):  # noqa: ANN001, ANN201 - Predictor.rollout's signature
        x, v = super().rollout(layout, x0, v0, poses, dt)
        return x * float("nan"), v


def _dynamics(scene, predictor=None, inputs=None) -> LearnedDynamics:
    layout = SimpleNamespace(bodies=(*scene.link_names, *scene.env_names))  # all a reference predictor reads
    return LearnedDynamics(predictor or ConstantVelocity(), layout, inputs or KinematicInputs(scene), DT,
                           torch.device("cpu"))


def _episode(scene, frames: int = 5) -> tuple[ObjectState, np.ndarray]:
    x0 = scene.objects["bag"].vertices.astype(np.float32)
    v0 = np.tile(np.float32([0.0, 0.0, 0.1]), (len(x0), 1))
    home = scene.home_action()
    return ObjectState(x0, v0), np.stack([home + np.float32(k * 0.001) for k in range(frames)]).astype(np.float32)


def _stepped(dynamics, initial: ObjectState, actions: np.ndarray) -> np.ndarray:
    """x (T, N, 3) of stepping through the actions from `initial`."""
    dynamics.start(initial, actions[0])
    states = [initial]
    for a in actions[1:]:
        states.append(dynamics.step(states[-1], a))
    return np.stack([s.x for s in states])


def test_newton_and_a_learned_predictor_answer_the_same_protocol(scene):
    assert issubclass(NewtonSimulator, Dynamics)
    assert isinstance(_dynamics(scene), Dynamics)


def test_a_learned_rollout_starts_at_its_state_and_steps_under_the_actions_poses(scene):
    initial, actions = _episode(scene)  # actions (T, 14)
    x0, v0 = initial.x, initial.v
    recorder = PoseRecorder()
    x, v = _dynamics(scene, recorder).rollout(initial, actions)
    assert x.shape == v.shape == (5, len(x0), 3)
    assert np.array_equal(x[0], x0) and np.array_equal(v[0], v0)
    assert np.allclose(x[4], x0 + 4 * DT * v0, atol=1e-6)
    links = scene.link_poses(actions)  # (T, L, 7): the robot's bodies follow the commanded actions
    assert np.allclose(recorder.poses[0, :, : len(scene.link_names)].numpy(), links, atol=1e-6)


def test_bad_batches_and_layouts_are_named(scene):
    x0 = scene.objects["bag"].vertices.astype(np.float32)
    state = ObjectState(x0, np.zeros_like(x0))
    home = scene.home_action()[None]
    with pytest.raises(ValueError, match="all of one length"):
        _dynamics(scene).rollout_batch([state, state], [np.repeat(home, 3, 0), np.repeat(home, 4, 0)])
    with pytest.raises(ValueError, match=r"\(B, T, 14\)"):
        _dynamics(scene).rollout(state, np.zeros((3, 7), np.float32))
    with pytest.raises(ValueError, match="layout bodies"):
        LearnedDynamics(ConstantVelocity(), SimpleNamespace(bodies=("table",)), KinematicInputs(scene), DT,
                        torch.device("cpu"))


@pytest.mark.parametrize("predictor", [ConstantVelocity(), Accelerating()], ids=["markov", "history"])
def test_stepping_gives_the_rollouts_frames(scene, predictor):
    initial, actions = _episode(scene, 6)
    dynamics = _dynamics(scene, predictor)
    x, _ = dynamics.rollout(initial, actions)
    np.testing.assert_allclose(_stepped(dynamics, initial, actions), x, rtol=0, atol=1e-6)
    if isinstance(predictor, Accelerating):  # x_5 = x_0 + 25 mm: stepping replayed the history, not 5 x 1 mm
        np.testing.assert_allclose(x[5] - x[0], np.tile([0.0, 0.0, 0.025], (len(x[0]), 1)), atol=1e-6)


def test_a_step_from_another_state_starts_a_new_history(scene):
    initial, actions = _episode(scene, 4)
    dynamics = _dynamics(scene, Accelerating())
    dynamics.start(initial, actions[0])
    first = dynamics.step(initial, actions[1])
    moved = ObjectState(first.x + np.float32(0.01), first.v)
    after = dynamics.step(moved, actions[2])  # not the state it gave: the history starts again from `moved`
    np.testing.assert_allclose(after.x, moved.x + np.float32([0.0, 0.0, 1e-3]), atol=1e-6)
    np.testing.assert_allclose(dynamics.step(after, actions[3]).x, moved.x + np.float32([0.0, 0.0, 4e-3]), atol=1e-6)


def test_recorded_inputs_are_stepped_frame_by_frame_and_answer_their_actions_only(scene):
    initial, actions = _episode(scene, 5)
    recorded = KinematicInputs(scene).poses(actions[None])[0] + np.float32(0.5)  # not the kinematics: as recorded
    inputs = RecordedInputs(actions, recorded, (*scene.link_names, *scene.env_names))
    recorder = PoseRecorder()
    dynamics = _dynamics(scene, recorder, inputs)
    x, _ = dynamics.rollout(initial, actions)
    assert np.array_equal(recorder.poses[0].numpy(), recorded)
    dynamics.start(initial, actions[0])
    state = initial
    for k in (1, 2):
        state = dynamics.step(state, actions[k])
        assert np.array_equal(recorder.poses[0].numpy(), recorded[k - 1:k + 1])  # frames k-1, k of the recording
    np.testing.assert_allclose(state.x, x[2], atol=1e-6)
    with pytest.raises(ValueError, match="not the recorded ones"):
        dynamics.rollout(initial, actions[::-1])
    with pytest.raises(ValueError, match="not the recorded ones"):
        dynamics.rollout(initial, np.concatenate([actions, actions[-1:]]))  # past the recording's end
    with pytest.raises(ValueError, match=r"poses \(T, \d+, 7\)"):
        RecordedInputs(actions, recorded[:-1], inputs.bodies)


def test_bad_steps_are_named(scene):
    initial, actions = _episode(scene, 3)
    dynamics = _dynamics(scene)
    with pytest.raises(RuntimeError, match="before start"):
        dynamics.step(initial, actions[1])
    with pytest.raises(ValueError, match=r"must be \(14,\)"):
        dynamics.start(initial, actions[:2])
    dynamics.start(initial, actions[0])
    with pytest.raises(ValueError, match=r"must be \(14,\)"):
        dynamics.step(initial, actions[1, :7])
    dynamics.predictor = Diverging()
    with pytest.raises(FloatingPointError, match="frame 1"):
        dynamics.step(initial, actions[1])
    with pytest.raises(RuntimeError, match="before start"):  # a failed step ends the episode
        dynamics.step(initial, actions[1])


class PastRecorder(ConstantVelocity):
    """Constant velocity with a 4-frame history that keeps the past frames it is given; episode 1 of the first call
    diverges at its second step."""

    history = 4

    def __init__(self) -> None:
        self.pasts = []

    def rollout(self, layout, x0, v0, poses, dt, past=None):  # noqa: ANN001, ANN201 - a history model's signature
        self.pasts.append(past)
        x, v = super().rollout(layout, x0, v0, poses, dt)
        if len(self.pasts) == 1:
            x[1, 1:] = float("nan")
        return x, v


def test_a_restart_after_a_divergence_gives_a_history_model_the_frames_before_it():
    """Episode 0 goes on from frame 2 with its recorded frame -1 and its predicted frames 0, 1 as history (planted bug
    caught: restarting from the recorded past only, or with none, would start it from a bag that jumped)."""
    n, t = 5, 6
    x0 = np.random.default_rng(0).random((2, n, 3)).astype(np.float32)
    v0 = np.full((2, n, 3), 0.1, np.float32)
    poses = np.zeros((2, t, 1, 7), np.float32)
    past = (x0[:, None] - DT * v0[:, None], v0[:, None], poses[:, :1])
    predictor = PastRecorder()
    x, _ = finite_rollout(predictor, None, x0, v0, poses, DT, torch.device("cpu"), past)
    assert len(predictor.pasts) == 2 and np.isnan(x[1, 2:]).all() and np.isfinite(x[0]).all()
    np.testing.assert_array_equal(predictor.pasts[0].x.numpy(), past[0])
    again = predictor.pasts[1].x.numpy()  # (1, 3, N, 3): frames -1, 0, 1 of episode 0
    np.testing.assert_allclose(again[0], np.stack([past[0][0, 0], x0[0], x[0, 1]]), atol=1e-7)
