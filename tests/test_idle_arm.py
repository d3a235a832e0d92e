"""An arm the task program does not move holds `scene.robot.idle_q` (default: the home posture) for the whole episode,
and the arm the task moves plans the same way whatever the idle arm does."""

import numpy as np
import pytest

from tests.conftest import load_params
from wc.config import ParamsError, load_section
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.tasks.base import EpisodeSpec, get_task

PARKED = [2.5, 1.57, -1.3485, 0.0, 0.0, 0.0]  # joint 1 turned back: the left wrist ~0.7 m from the bag


def _lift_actions(*overrides: str) -> tuple[np.ndarray, np.ndarray, object]:
    params = load_params(*overrides)
    scene = build_scene(load_section(params, "scene", SceneConfig), ("bag",))
    task = get_task("lift_handle", params)
    spec = EpisodeSpec("lift_handle", 5, 0, 0.08, 0.19)
    initial = task.initial_state(scene, spec, np.random.default_rng(0))
    start = task.settle_action(scene, spec, initial)
    return start, task.actions(scene, initial, spec, start, 0.04), scene


def test_the_idle_arm_defaults_to_home_and_holds_the_parked_posture_when_given():
    start, actions, scene = _lift_actions()
    np.testing.assert_allclose(actions[:, 0:6], np.broadcast_to(scene.home_q, (len(actions), 6)), atol=1e-6)
    parked_start, parked, parked_scene = _lift_actions(f"scene.robot.idle_q={PARKED}")
    np.testing.assert_allclose(parked[:, 0:6], np.broadcast_to(PARKED, (len(parked), 6)), atol=1e-6)
    np.testing.assert_array_equal(parked[:, 7:], actions[:, 7:])  # the right arm's plan is the same
    np.testing.assert_array_equal(parked_start[7:], start[7:])
    left6 = parked_scene.link_names.index("left_link6")
    bag_centre = scene.objects["bag"].vertices.mean(axis=0)[:2]
    gap = np.linalg.norm(parked_scene.link_poses(parked)[:, left6, :2] - bag_centre, axis=-1)
    assert gap.min() > 0.5  # the idle wrist is well clear of the bag


def test_an_idle_posture_outside_the_joint_limits_is_named():
    with pytest.raises((ValueError, ParamsError), match="idle_q"):
        load_section(load_params("scene.robot.idle_q=[3.0, 1.57, -1.3485, 0.0, 0.0, 0.0]"), "scene", SceneConfig)
