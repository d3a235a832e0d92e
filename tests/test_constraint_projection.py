"""The joint constraint projection of the generation path (wc.expand.constraints): after it every cloth edge is within
its limits and no cloth vertex is inside the table or a robot box, pinned vertices stay, and a contact correction
injects no velocity (only the velocity into the surface is removed)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from wc.expand.constraints import ConstraintProjection, edge_colours
from wc.expand.contact import Bodies
from wc.scene.scene import build_scene

DT = 0.04


@pytest.fixture(scope="module")
def scene(scene_cfg):
    return build_scene(scene_cfg, ["bag"])


def _frame_bodies(projection: ConstraintProjection, scene, like: torch.Tensor) -> list[Bodies]:
    link_poses = scene.link_poses(np.stack([scene.home_action()] * like.shape[0]))[:, None]  # (B, 1, L, 7)
    boxes = projection.contacts.boxes(link_poses, like)
    return [Bodies(boxes.pos[:, 0], boxes.rot[:, 0], boxes.normals, boxes.offsets)]


def _table_top(scene) -> float:
    return float(scene.table.center_m[2] + scene.table.half_extents_m[2])


def test_edge_colours_share_no_vertex(scene):
    edges = ConstraintProjection(scene).edges
    colours = edge_colours(edges)
    assert sum(len(c) for c in colours) == len(edges) and len(colours) < 16
    for c in colours:
        ends = edges[c].ravel()
        assert len(np.unique(ends)) == len(ends)


@pytest.mark.slow
def test_stretched_sunken_cloth_ends_within_its_limits_and_out_of_the_table(scene):
    projection = ConstraintProjection(scene, iterations=200)
    rest = torch.as_tensor(scene.objects["bag"].vertices, dtype=torch.float64)
    rng = np.random.default_rng(0)
    centre = rest.mean(0)
    x = torch.stack([centre + 1.3 * (rest - centre), centre + (rest - centre) * 0.8])  # stretched / compressed
    x = x + torch.as_tensor(rng.normal(0, 0.004, x.shape))
    x[..., 2] -= x[..., 2].amin(dim=1, keepdim=True) - (_table_top(scene) - 0.01)  # each lowest vertex 1 cm in
    bodies = _frame_bodies(projection, scene, x)
    assert (projection.strain(x) > 0.15).all()
    out, _, report = projection.project(x, x.clone(), torch.zeros_like(x), DT, bodies)
    assert report.converged.all() and (report.strain_before > report.strain_after).all()
    lo, hi = (torch.as_tensor(b) for b in projection.bounds)
    e = torch.as_tensor(projection.edges)
    length = (out[:, e[:, 1]] - out[:, e[:, 0]]).norm(dim=-1)
    assert (length >= lo - 1e-4).all() and (length <= hi + 1e-4).all()
    assert (out[..., 2] >= _table_top(scene) - 1e-4).all()
    assert report.depth_before.min() > 0.009 and report.depth_after.max() <= 1e-4


def test_a_contact_push_injects_no_velocity(scene):
    projection = ConstraintProjection(scene, edge_ratio=(0.05, 20.0))  # edges never bind: the contact part alone
    rest = torch.as_tensor(scene.objects["bag"].vertices, dtype=torch.float64)[None]
    x = rest.clone()
    x[..., 2] -= x[..., 2].min() - (_table_top(scene) - 0.005)  # rigidly 5 mm into the table
    bodies = _frame_bodies(projection, scene, x)
    lifted, still, _ = projection.project(x, x.clone(), torch.zeros_like(x), DT, bodies)
    assert (lifted[..., 2] >= _table_top(scene) - 1e-4).all()
    assert torch.equal(still, torch.zeros_like(x))  # pushed out, not launched upwards
    v = torch.zeros_like(x)
    v[..., 0], v[..., 2] = 0.1, -0.2  # sliding and sinking
    out, v_out, _ = projection.project(x, x.clone(), v, DT, bodies)
    pushed = (out - x).norm(dim=-1) > 0
    assert pushed.any()
    assert torch.allclose(v_out[pushed][:, 2], torch.zeros(int(pushed.sum()), dtype=x.dtype))  # into-surface removed
    assert torch.allclose(v_out[..., 0], v[..., 0])  # tangential motion kept
    assert (v_out[~pushed] == v[~pushed]).all()


def test_pinned_vertices_stay_where_the_pads_hold_them(scene):
    projection = ConstraintProjection(scene, iterations=100)
    rest = torch.as_tensor(scene.objects["bag"].vertices, dtype=torch.float64)[None]
    x = rest.clone()
    handle = torch.as_tensor(next(g for name, g in scene.objects["bag"].groups.items() if name.startswith("handle")))
    pinned = torch.zeros(x.shape[:2], dtype=torch.bool)
    pinned[0, handle[:3]] = True
    x[0, pinned[0]] += torch.tensor([0.0, 0.0, 0.015], dtype=x.dtype)  # the pads lifted these 1.5 cm in a frame
    out, _, report = projection.project(x, x.clone(), torch.zeros_like(x), DT, [], pinned)
    assert torch.equal(out[pinned], x[pinned])
    assert report.converged.all()


def test_final_edge_passes_restore_the_edges_an_unconverged_loop_left(scene):
    rest = torch.as_tensor(scene.objects["bag"].vertices, dtype=torch.float64)
    centre = rest.mean(0)
    x = (centre + 2.0 * (rest - centre))[None]  # every edge twice its rest length
    v = torch.zeros_like(x)
    one_pass = ConstraintProjection(scene, iterations=1)
    _, _, short = one_pass.project(x, x.clone(), v, DT, [])
    guarded = ConstraintProjection(scene, iterations=1, final_edge_passes=300)
    out, v_out, report = guarded.project(x, x.clone(), v, DT, [])
    assert not short.converged.all() and short.strain_after.max() > 0.15  # one pass does not bring them back
    assert report.converged.all() and report.strain_after.max() < 0.12  # the final passes do (within 0.1 mm)
    assert torch.allclose(v_out, (out - x) / DT)  # velocities follow the edge corrections
    with pytest.raises(ValueError, match="final_edge_passes"):
        ConstraintProjection(scene, final_edge_passes=-1)
