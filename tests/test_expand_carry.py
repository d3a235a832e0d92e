"""expand.pad_carry: cloth between closed finger pads is held, moves with the pads and stays pinned through the
joint projection; cloth near open pads is not held."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import load_params
from wc.config import load_section
from wc.expand.carry import PadCarry, held_between_pads
from wc.expand.constraints import JointStepProjection
from wc.scene.scene import build_scene
from wc.validate.predicates import finger_pad_boxes

LIFT = np.array([0.0, 0.0, 0.03])  # the whole robot raised 3 cm between the two frames


@pytest.fixture(scope="module")
def scene(scene_cfg):
    return build_scene(scene_cfg)


def _poses(scene, opening_m: float) -> np.ndarray:
    """(1, L, 7) link poses with the right gripper opened to opening_m, arms at home."""
    action = np.zeros((1, 14), np.float32)
    action[0, 13] = opening_m
    return scene.link_poses(action)


def _between_right_pads(scene, poses: np.ndarray) -> np.ndarray:
    centre, _, _ = finger_pad_boxes(scene, poses, "right")
    return centre[0].mean(axis=0)  # midway between the two pads


def _state(scene, point: np.ndarray) -> torch.Tensor:
    """(1, N, 3) the bag at rest with vertex 0 moved to `point`."""
    x = np.concatenate([m.vertices for m in scene.objects.values()]).astype(np.float64)
    x[0] = point
    return torch.as_tensor(x[None])


def test_only_closed_pads_hold_cloth(scene):
    closed, opened = _poses(scene, 0.004), _poses(scene, 0.08)
    assert held_between_pads(scene, _between_right_pads(scene, closed)[None, None], closed, 0.004).all()
    assert not held_between_pads(scene, _between_right_pads(scene, opened)[None, None], opened, 0.004).any()


def test_held_cloth_moves_with_the_pads_and_stays_pinned(scene):
    before = _poses(scene, 0.004)
    after = before.copy()
    after[..., :3] += LIFT
    x_prev = _state(scene, _between_right_pads(scene, before))
    predicted = x_prev.clone()  # the model let the strap slip: nothing moved
    dt = 0.04
    x, v, pinned = PadCarry(scene, 0.004).apply(x_prev, predicted, torch.zeros_like(predicted), dt, before, after)
    assert pinned[0, 0] and int(pinned.sum()) == 1
    assert torch.allclose(x[0, 0] - x_prev[0, 0], torch.as_tensor(LIFT), atol=1e-6)
    assert torch.allclose(v[0, 0], torch.as_tensor(LIFT) / dt, atol=1e-4)
    assert torch.equal(x[0, 1:], predicted[0, 1:])  # the rest of the cloth is the model's
    # through the joint projection: the stretched edges at vertex 0 are corrected by its neighbours only
    joint = JointStepProjection(scene, (0.9, 1.1), 50, PadCarry(scene, 0.004))
    boxes = joint.boxes(np.stack([before, after], axis=1), x_prev)
    x_out, _ = joint.project(x_prev, predicted, torch.zeros_like(predicted), dt, boxes, 1, after, before)
    assert torch.allclose(x_out[0, 0], x[0, 0], atol=1e-9) and joint.stats["carried_vertex_steps"] == 1
    assert not torch.allclose(x_out[0, 1:], predicted[0, 1:])  # its neighbours followed it up


def test_bad_radius_and_projection_are_errors(scene):
    from wc.config import ParamsError
    from wc.expand.config import ExpandConfig

    with pytest.raises(ValueError, match="radius must be positive"):
        PadCarry(scene, 0.0)
    params = load_params("expand.pad_carry=true", "expand.projection=contact")
    with pytest.raises(ParamsError, match="pad_carry needs projection 'joint'"):
        load_section(params, "expand", ExpandConfig)
