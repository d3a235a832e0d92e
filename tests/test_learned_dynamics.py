"""A learned predictor as `wc.dynamics.Dynamics` (wc.model.learned_dynamics): the Newton simulator's call - frame-0
object states and 14-D actions in, (x, v) per frame out - with the robot's poses from the scene's kinematics."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from wc.dynamics import Dynamics, ObjectState
from wc.eval.predictors import ConstantVelocity
from wc.model.learned_dynamics import LearnedDynamics
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


def _dynamics(scene, predictor=None) -> LearnedDynamics:
    layout = SimpleNamespace(bodies=(*scene.link_names, *scene.env_names))  # all a reference predictor reads
    return LearnedDynamics(predictor or ConstantVelocity(), layout, scene, DT, torch.device("cpu"))


def test_newton_and_a_learned_predictor_answer_the_same_protocol(scene):
    assert issubclass(NewtonSimulator, Dynamics)
    assert isinstance(_dynamics(scene), Dynamics)


def test_a_learned_rollout_starts_at_its_state_and_steps_under_the_actions_poses(scene):
    x0 = scene.objects["bag"].vertices.astype(np.float32)
    v0 = np.tile(np.float32([0.0, 0.0, 0.1]), (len(x0), 1))
    home = scene.home_action()
    actions = np.stack([home + np.float32(k * 0.001) for k in range(5)]).astype(np.float32)  # (T, 14)
    recorder = PoseRecorder()
    x, v = _dynamics(scene, recorder).rollout(ObjectState(x0, v0), actions)
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
        LearnedDynamics(ConstantVelocity(), SimpleNamespace(bodies=("table",)), scene, DT, torch.device("cpu"))
