"""The generation path's self-contact separation (wc.expand.self_contact) and self-crossing rollback (wc.expand.untangle): after it no cloth edge crosses the cloth, only the
vertices of a crossing (and their neighbours) move back towards the previous state, along their own step, and their
velocities shrink by the same factor (no velocity invented)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from wc.expand.self_contact import SelfContactSeparation
from wc.expand.untangle import SelfIntersectionGuard


def _square(x0: float, x1: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x0, x0, z], [x1, x0, z], [x1, x1, z], [x0, x1, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _scene() -> SimpleNamespace:
    """One cloth object of two parallel sheets (the top one inside the bottom one's outline) and a rigid cube."""
    bottom, fb = _square(-0.05, 0.15, 0.0)
    top, ft = _square(0.0, 0.1, 0.02)
    sheet = SimpleNamespace(vertices=np.concatenate([bottom, top]), faces=np.concatenate([fb, ft + 4]))
    cube = SimpleNamespace(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]]))
    return SimpleNamespace(objects={"sheet": sheet, "cube": cube}, object_kinds={"sheet": "cloth", "cube": "rigid"},
                           vertex_slices=lambda: {"sheet": slice(0, 8), "cube": slice(8, 11)})


def _state(scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """x_prev (1, 11, 3), a step x that pushes a top-sheet corner through the bottom sheet, and v = (x - x_prev)/dt."""
    x_prev = torch.as_tensor(np.concatenate([scene.objects["sheet"].vertices, scene.objects["cube"].vertices]))[None]
    x = x_prev.clone()
    x[0, :, 0] += 0.001  # everything drifts a little
    x[0, 4, 2] = -0.01  # the top sheet's first corner goes 1 cm below the bottom sheet
    return x_prev, x, (x - x_prev) / 0.04


def test_a_crossing_step_is_rolled_back_until_no_edge_crosses():
    scene = _scene()
    guard = SelfIntersectionGuard(scene, rounds=4)
    x_prev, x, v = _state(scene)
    assert guard.crossing_vertices(x[0].numpy()).any()
    x_out, v_out = guard.apply(x_prev, x, v)
    assert not guard.crossing_vertices(x_out[0].numpy()).any()
    moved = (x_out - x).norm(dim=-1)[0] > 0
    assert moved[4] and not moved[8:].any(), "the crossing corner rolls back; the rigid cube is never touched"
    a = (x_out - x_prev)[0, moved, 0] / (x - x_prev)[0, moved, 0]  # every vertex's step has x = 1 mm
    assert torch.allclose(a, a[0]) and 0 <= float(a[0]) < 1
    assert torch.allclose(x_out[0, moved], (x_prev + a[0] * (x - x_prev))[0, moved])  # a shorter step along its own
    assert torch.allclose(v_out[0, moved], a[0] * v[0, moved])  # velocity scaled the same: none invented
    assert torch.equal(x_out[0, ~moved], x[0, ~moved]) and torch.equal(v_out[0, ~moved], v[0, ~moved])
    assert guard.stats["steps_with_crossings"] == 1 and guard.stats["unresolved_steps"] == 0


def test_a_crossing_free_step_is_kept_and_a_crossing_previous_state_is_reported():
    scene = _scene()
    guard = SelfIntersectionGuard(scene)
    x_prev, x, v = _state(scene)
    clean = x_prev + 0.001
    out, out_v = guard.apply(x_prev, clean, v)
    assert torch.equal(out, clean) and torch.equal(out_v, v) and guard.stats["steps_with_crossings"] == 0
    guard.apply(x, x.clone(), v)  # the previous state itself crosses: nothing to roll back to
    assert guard.stats["unresolved_steps"] == 1


def test_rounds_must_be_positive():
    with pytest.raises(ValueError, match="rounds"):
        SelfIntersectionGuard(_scene(), rounds=0)


def test_self_contact_pushes_a_crossed_vertex_back_to_its_side_a_gap_away():
    scene = _scene()
    separation = SelfContactSeparation(scene, gap_m=0.002, filter_rings=1)
    x_prev, x, _ = _state(scene)
    pairs = separation.pairs(x)
    out = x.clone()
    inv_mass = torch.ones(x.shape[:2], dtype=x.dtype)
    inv_mass[0, 8:] = 0.0  # the rigid rows never take part
    first_shortfall = separation.separate(x_prev, out.clone(), pairs, inv_mass)[1]
    for _ in range(30):
        out, shortfall = separation.separate(x_prev, out, pairs, inv_mass)
    assert float(first_shortfall[0]) > 0.01 and float(shortfall[0]) < 1e-6
    assert not SelfIntersectionGuard(scene).crossing_vertices(out[0].numpy()).any()
    p0, p1, p2 = out[0, 0], out[0, 1], out[0, 2]  # the bottom triangle under the corner
    normal = torch.linalg.cross(p1 - p0, p2 - p0)
    height = float(((out[0, 4] - p0) * normal / normal.norm()).sum())
    assert height >= 0.002 - 1e-6  # the corner is back above the bottom sheet (its side before the step), a gap away
    assert torch.equal(out[0, 8:], x[0, 8:])


def test_self_contact_leaves_separated_layers_and_mesh_neighbours_alone():
    scene = _scene()
    separation = SelfContactSeparation(scene, gap_m=0.002, filter_rings=1)
    x_prev, _, _ = _state(scene)
    pairs = separation.pairs(x_prev)  # the sheets are 2 cm apart; a vertex's own triangles are filtered out
    out, shortfall = separation.separate(x_prev, x_prev.clone(), pairs, torch.ones(x_prev.shape[:2], dtype=x_prev.dtype))
    assert torch.equal(out, x_prev) and float(shortfall[0]) == 0.0
    with pytest.raises(ValueError, match="gap_m"):
        SelfContactSeparation(scene, gap_m=0.0)
