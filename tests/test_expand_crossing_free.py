"""The bounded generation step (wc.expand.crossing_free): exact element distances, no step that leaves the cloth
crossing itself, layers moving together are not held back, velocities follow the positions, rigid rows untouched."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from wc.expand.config import ExpandConfig
from wc.expand.crossing_free import CrossingFreeStep, point_triangle_distance, segment_segment_distance
from wc.validate.self_intersection import crossing_edges, unique_edges

DT = 0.04


def _grid(n: int, size: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    g = np.stack(np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n)), -1).reshape(-1, 2)
    quads = [(i * n + j, i * n + j + 1, i * n + j + n + 1, i * n + j + n) for i in range(n - 1) for j in range(n - 1)]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    return np.c_[g, np.full(len(g), z)], faces


def _two_layers(n: int = 6, gap: float = 0.002) -> SimpleNamespace:
    """One cloth object of two stacked grids `gap` apart (a flat bag's walls) and a rigid 3-vertex object."""
    bottom, faces = _grid(n, 0.05, 0.0)
    top, _ = _grid(n, 0.05, gap)
    cloth = SimpleNamespace(vertices=np.concatenate([bottom, top]), faces=np.concatenate([faces, faces + len(bottom)]))
    rigid = SimpleNamespace(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]]))
    m = len(cloth.vertices)
    return SimpleNamespace(objects={"cloth": cloth, "rigid": rigid}, object_kinds={"cloth": "cloth", "rigid": "rigid"},
                           vertex_slices=lambda: {"cloth": slice(0, m), "rigid": slice(m, m + 3)})


def _crosses(scene: SimpleNamespace, x: torch.Tensor) -> bool:
    cloth = scene.objects["cloth"]
    faces = np.asarray(cloth.faces, np.int32)
    pts = x[: len(cloth.vertices)].numpy().astype(np.float32)
    return bool((crossing_edges(pts, faces, unique_edges(faces)) >= 0).any())


def _rest(scene: SimpleNamespace) -> torch.Tensor:
    return torch.as_tensor(np.concatenate([o.vertices for o in scene.objects.values()]))[None]


def test_distances_match_dense_sampling():
    torch.manual_seed(0)
    p, tri = torch.randn(50, 3, dtype=torch.float64), torch.randn(50, 3, 3, dtype=torch.float64)
    u = torch.rand(20000, 2, dtype=torch.float64)
    u = torch.where((u.sum(1) > 1)[:, None], 1 - u, u)
    samples = tri[:, :1] + u[None, :, :1] * (tri[:, 1:2] - tri[:, :1]) + u[None, :, 1:] * (tri[:, 2:] - tri[:, :1])
    sampled = (samples - p[:, None]).norm(dim=-1).amin(dim=1)
    exact = point_triangle_distance(p, tri)
    assert (exact <= sampled + 1e-12).all() and (sampled - exact).max() < 0.02
    above = torch.tensor([[0.2, 0.2, 0.5]], dtype=torch.float64)
    unit = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]], dtype=torch.float64)
    assert torch.allclose(point_triangle_distance(above, unit), torch.tensor([0.5], dtype=torch.float64))
    z = torch.zeros(1, 3, dtype=torch.float64)

    def seg(a: list[float]) -> torch.Tensor:
        return torch.tensor([a], dtype=torch.float64)

    assert float(segment_segment_distance(seg([-1, 0, 0]), seg([1, 0, 0]), seg([0, -1, 0.3]), seg([0, 1, 0.3]))) == \
        pytest.approx(0.3)  # skew, closest inside both
    assert float(segment_segment_distance(seg([0, 0, 0]), seg([1, 0, 0]), seg([0.5, 0.2, 0]), seg([2, 0.2, 0]))) == \
        pytest.approx(0.2)  # parallel, overlapping
    assert float(segment_segment_distance(z, seg([1, 0, 0]), seg([2, 0, 0]), seg([3, 1, 0]))) == pytest.approx(1.0)


def test_a_step_through_the_other_layer_is_stopped_short_of_it_without_new_velocity():
    scene = _two_layers()
    x_prev = _rest(scene)
    x = x_prev.clone()
    x[0, :, 0] += 0.001  # everything drifts a little
    top_centre = 36 + 14  # an inner vertex of the top grid
    x[0, top_centre] += torch.tensor([0.0013, 0.0007, -0.006], dtype=x.dtype)  # pushed 6 mm down, through the
    # bottom grid, and off the grid's lines (a step exactly along its edges is a touch the strict check does not count)
    v = (x - x_prev) / DT
    assert _crosses(scene, x[0])
    guard = CrossingFreeStep(scene)
    x_out, v_out = guard.apply(x_prev, x, v, DT)
    assert not _crosses(scene, x_out[0])
    assert float(x_out[0, top_centre, 2]) > 0.0, "the pushed vertex stays above the bottom layer"
    assert torch.allclose(v_out, v + (x_out - x) / DT), "velocities follow the position correction"
    assert (v_out - v)[0, top_centre, 2] > 0, "the correction removes downward speed, it adds none"
    assert torch.equal(x_out[0, 72:], x[0, 72:]), "rigid rows are never touched"
    assert guard.stats["limited_steps"] == 1
    far = (x_prev[0, :72] - x_prev[0, top_centre]).norm(dim=-1) > 0.03
    assert torch.allclose(x_out[0, :72][far], x[0, :72][far]), "vertices far from the crossing keep their step"


def test_layers_moving_together_are_not_held_back():
    scene = _two_layers(gap=0.0005)
    x_prev = _rest(scene)
    x = x_prev.clone()
    x[0, :72] += torch.tensor([0.004, -0.002, 0.006], dtype=x.dtype)  # 7 mm, 14 x the layers' distance, together
    x_out, v_out = CrossingFreeStep(scene).apply(x_prev, x, torch.zeros_like(x), DT)
    assert torch.allclose(x_out, x) and torch.allclose(v_out, torch.zeros_like(x))


def test_random_steps_never_leave_a_crossing():
    scene = _two_layers(n=5, gap=0.002)
    gen = torch.Generator().manual_seed(1)
    x = _rest(scene).repeat(2, 1, 1)
    guard = CrossingFreeStep(scene, rounds=2)
    crossed_targets = 0
    for _ in range(6):
        target = x + 0.0015 * torch.randn(x.shape, generator=gen, dtype=x.dtype)
        crossed_targets += sum(_crosses(scene, t) for t in target)
        x, _ = guard.apply(x, target, torch.zeros_like(x), DT)
        assert not any(_crosses(scene, e) for e in x)
    assert crossed_targets > 0, "the test must offer crossing steps"


def test_non_finite_episodes_pass_through_and_bad_settings_are_refused():
    scene = _two_layers(n=3)
    x_prev = _rest(scene).repeat(2, 1, 1)
    x = x_prev + 0.001
    x[1, 0] = float("nan")
    x_out, _ = CrossingFreeStep(scene).apply(x_prev, x, torch.zeros_like(x), DT)
    assert torch.allclose(x_out[0], x[0]) and torch.isnan(x_out[1, 0]).all()
    with pytest.raises(ValueError, match="share"):
        CrossingFreeStep(scene, share=1.0)
    base = dict(task="lift_handle", target_trajectories=2, max_attempts=2, batch_size=1, yaw_range_deg=(0, 0),
                shift_x_range_m=(0, 0), shift_y_range_m=(0, 0))
    with pytest.raises(ValueError, match="untangle must be"):
        ExpandConfig(**base, untangle="yes").validate()
    with pytest.raises(ValueError, match="untangle_share"):
        ExpandConfig(**base, untangle="bounded", untangle_share=0.0).validate()
    with pytest.raises(ValueError, match="needs projection 'joint'"):
        ExpandConfig(**base, untangle="bounded", projection="contact").validate()


def test_bounded_then_rollback_leaves_no_crossing_and_reports_both_guards():
    from wc.expand.untangle import SelfIntersectionGuard

    scene = _two_layers(n=5, gap=0.002)
    gen = torch.Generator().manual_seed(2)
    x = _rest(scene)
    rollback = SelfIntersectionGuard(scene)
    guard = CrossingFreeStep(scene, rounds=1, passes=1, hold=False, then=rollback)  # one pass: leftovers likely
    for _ in range(4):
        target = x + 0.002 * torch.randn(x.shape, generator=gen, dtype=x.dtype)
        x, _ = guard.apply(x, target, torch.zeros_like(x), DT)
        assert not _crosses(scene, x[0])
    assert guard.stats["held_vertex_steps"] == 0 and guard.stats["limited_steps"] > 0
    assert rollback.stats["unresolved_steps"] == 0
