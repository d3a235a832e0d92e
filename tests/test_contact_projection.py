"""Contact projection (wc.expand.contact): its distances are the validation's, projected cloth passes the
penetration check against the table, robot boxes and rigid objects (held and predicted), untouched vertices and
velocities stay as predicted, moved ones get v = (x_next - x_prev) / dt, and a wrapped real predictor that sinks
through the table stays on it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import load_params
from tests.synthetic_store import HELD_SPHERE
from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.eval.predictors import ConstantVelocity
from wc.expand.contact import Bodies, ContactProjectedPredictor, ContactProjection
from wc.model.layout import scene_layout
from wc.scene.scene import build_scene
from wc.validate.config import ValidateConfig
from wc.validate.predicates import (Episode, box_signed_distance, cloth_rows, convex_depth, convex_planes,
                                    penetration, quat_matrices, rigid_poses, robot_boxes, table_and_robot_distance)

DT = 0.04
DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]


@pytest.fixture(scope="module")
def params() -> dict:
    return load_params()


def _strict(params) -> ValidateConfig:
    """The validation config with a 1 um penetration tolerance."""
    return load_section({**params, "validate": {**params["validate"], "penetration_tol_m": 1e-6}}, "validate",
                        ValidateConfig)


def _random_quats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


@pytest.mark.parametrize("device", DEVICES)
def test_box_depth_is_the_validations_and_the_exit_lands_on_the_union_surface(params, scene_cfg, device):
    rng = np.random.default_rng(0)
    scene = build_scene(scene_cfg, ["bag"])
    B, N = 2, 600
    actions = np.stack([scene.home_action(), scene.home_action(right_opening_m=0.05)])
    actions[1, 7:13] += rng.uniform(-0.3, 0.3, 6)
    link_poses = scene.link_poses(actions)  # (B, L, 7)
    centre, quat, half = robot_boxes(scene, link_poses)
    # points around the right wrist and the table top: many inside one box or several overlapping ones
    wrist = centre[:, [scene.link_names.index("right_link6")]]
    points = np.concatenate([wrist + rng.uniform(-0.12, 0.12, (B, N, 3)),
                             rng.uniform([-0.3, -0.3, -0.02], [0.3, 0.3, 0.01], (B, N, 3))], axis=1)
    proj = ContactProjection(scene)
    pts = torch.as_tensor(points, device=device)
    bodies = proj.boxes(link_poses[:, None], pts)
    frame = Bodies(bodies.pos[:, 0], bodies.rot[:, 0], bodies.normals, bodies.offsets)
    sd = frame.depth(pts)[0].cpu().numpy()  # (B, 2N, 1 + K): the table first
    ref = box_signed_distance(points[:, :, None], centre[:, None], quat[:, None], half)  # (B, 2N, K) robot
    inside = ref < 0
    assert ((sd[..., 1:] < 0) == inside).all() and sd[..., 1:][inside] == pytest.approx(ref[inside], abs=1e-9)
    union = table_and_robot_distance(scene, points, link_poses)
    assert (union < 0).sum() > 200 and ((sd < 0).sum(-1) > 1).sum() > 20  # inside, some in overlapping boxes
    assert sd.min(-1)[union < 0] == pytest.approx(union[union < 0], abs=1e-9)  # the deepest body's depth
    out = proj.push_out(pts, [frame]).cpu().numpy()
    after = table_and_robot_distance(scene, out, link_poses)
    assert after.min() > -1e-9  # out of every body ...
    assert np.abs(after[union < 0]).max() < 1e-9  # ... onto the union's surface, not beyond
    assert np.array_equal(out[union >= 0], points[union >= 0])
    moved = np.linalg.norm(out - points, axis=-1)
    assert (moved[union < 0] >= -union[union < 0] - 1e-9).all()  # no shorter way out than the depth


def _bag_inside_table_and_wrist(scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cloth state x (N, 3) with rows pushed into the table and into the right wrist box at action home, and the
    link poses (L, 7)."""
    link_poses = scene.link_poses(scene.home_action())
    x = scene.objects["bag"].vertices.astype(np.float64).copy()
    x[:20, 2] = scene.table.top_z - rng.uniform(0.001, 0.02, 20)  # sunk into the table
    centre, quat, half = robot_boxes(scene, link_poses[None], ("right_link6",))
    local = rng.uniform(-0.8, 0.8, (15, 3)) * half[0]
    x[20:35] = centre[0, 0] + (quat_matrices(quat[0, 0]) @ local.T).T  # inside the wrist box
    return x, link_poses


@pytest.mark.parametrize("device", DEVICES)
def test_projection_clears_table_and_robot_and_fixes_velocity_of_moved_vertices_only(params, scene_cfg, device):
    scene = build_scene(scene_cfg, ["bag"])
    rng = np.random.default_rng(1)
    x, link_poses = _bag_inside_table_and_wrist(scene, rng)
    cfg = _strict(params)
    ep = lambda a: Episode(a[None], a[None], np.zeros((1, 14)), link_poses[None], DT)  # noqa: E731
    assert penetration(scene, ep(x), cfg) == 0  # the case penetrates
    proj = ContactProjection(scene)
    xs = torch.as_tensor(np.stack([x, scene.objects["bag"].vertices]), device=device)  # episode 1: clear
    x_prev = xs + 0.001
    v = torch.full_like(xs, 0.25)
    boxes = proj.boxes(np.stack([link_poses, link_poses])[:, None], xs)
    px, pv = proj.project(x_prev, xs, v, DT, boxes, 0, np.stack([link_poses, link_poses]))
    px, pv = px.cpu().numpy(), pv.cpu().numpy()
    assert penetration(scene, ep(px[0]), cfg) is None
    depth = table_and_robot_distance(scene, px[:1], link_poses[None])
    assert depth.min() > -1e-6 and np.isclose(depth[0, :35], 0.0, atol=1e-6).all()  # on the surface, not beyond
    moved = ~np.isclose(px[0], x).all(axis=1)
    assert moved[:35].all() and not moved[35:].any()
    assert np.array_equal(px[1], scene.objects["bag"].vertices.astype(np.float64))  # nothing to do there
    assert pv[0, moved] == pytest.approx((px[0, moved] - x_prev[0].cpu().numpy()[moved]) / DT)
    assert np.all(pv[0, ~moved] == 0.25) and np.all(pv[1] == 0.25)


def test_projection_clears_held_and_predicted_rigid_objects(params, scene_cfg):
    cfg = _strict(params)
    rng = np.random.default_rng(2)
    for objects, held in ((["bag"], HELD_SPHERE), (["bag", "cube"], None)):
        scene = build_scene(scene_cfg, objects, held=held)
        link_poses = scene.link_poses(scene.home_action())
        rows = cloth_rows(scene)
        x = np.concatenate([scene.objects[o].vertices.astype(np.float64) for o in objects])
        if "cube" in objects:  # the predicted cube, turned and lifted off the table
            cube = scene.vertex_slices()["cube"]
            q = _random_quats(rng, ())
            x[cube] = (quat_matrices(q) @ x[cube].T).T + [0.0, 0.0, 0.2]
        body, mesh, pos, rot = rigid_poses(scene, Episode(x[None], x[None], np.zeros((1, 14)), link_poses[None], DT))[0]
        local = rng.uniform(-0.5, 0.5, (10, 3)) * np.abs(mesh.vertices).max(0)  # well inside the convex body
        x[rows[:10]] = pos[0] + (rot[0] @ local.T).T
        planes = convex_planes(mesh.vertices, mesh.faces, body)
        assert convex_depth(x[None, rows], pos, rot, planes)[0] > 1e-3
        proj = ContactProjection(scene)
        xt = torch.as_tensor(x[None])
        px, _ = proj.project(xt, xt, torch.zeros_like(xt), DT, proj.boxes(link_poses[None, None], xt), 0,
                             link_poses[None])
        px = px.numpy()
        assert convex_depth(px[:, rows], pos, rot, planes)[0] < 1e-6, body
        assert penetration(scene, Episode(px, px, np.zeros((1, 14)), link_poses[None], DT), cfg) is None, body
        others = np.setdiff1d(np.arange(len(x)), rows)
        assert np.array_equal(px[0, others], x[others])  # rigid rows are never moved


@pytest.fixture(scope="module")
def layout_and_scene(synthetic_store, params, scene_cfg):
    path = synthetic_store(params, [("fall", "train")], frames=3)
    scene = build_scene(scene_cfg, ["bag"])
    return scene_layout(TrajectoryStore(path), ["bag"], list(scene.link_names), 0.02), scene


@pytest.mark.parametrize("device", DEVICES)
def test_wrapped_predictor_stays_on_the_table_and_matches_its_velocity_rule(layout_and_scene, params, device):
    layout, scene = layout_and_scene
    layout = layout.to(device)
    bag = torch.as_tensor(scene.objects["bag"].vertices + np.float32([0.0, 0.0, 0.004]))
    x0 = torch.stack([bag, bag + torch.tensor([0.02, 0.0, 0.0])]).to(device)
    v0 = torch.zeros_like(x0)
    v0[..., 2] = -0.3  # constant velocity: straight through the table
    actions = np.repeat(scene.home_action()[None], 6, axis=0)
    env = np.broadcast_to(scene.env_poses(), (6, 1, 7))
    poses = torch.as_tensor(np.concatenate([scene.link_poses(actions), env], axis=1)[None].repeat(2, 0),
                            device=device)
    plain = ConstantVelocity().rollout(layout, x0, v0, poses, DT)[0].cpu().numpy()
    link = scene.link_poses(actions)[1:]
    assert table_and_robot_distance(scene, plain[0], link).min() < -0.02  # without: 2+ cm into the table
    x, v = ContactProjectedPredictor(ConstantVelocity(), scene).rollout(layout, x0, v0, poses, DT)
    assert x.shape == (2, 5, *x0.shape[1:]) and x.device.type == device
    x, v = x.cpu().numpy(), v.cpu().numpy()
    for b in range(2):
        assert table_and_robot_distance(scene, x[b], link).min() > -1e-6
        assert penetration(scene, Episode(x[b], v[b], actions[1:], link, DT), _strict(params)) is None
    prev = np.concatenate([x0.cpu().numpy()[:, None], x[:, :-1]], axis=1)
    assert v == pytest.approx((x - prev) / DT, abs=1e-4)  # every vertex moved (fell or was stopped)
    on_table = np.abs(x[..., 2] - scene.table.top_z) < 1e-6  # (B, T, N)
    resting = on_table[:, 1:] & on_table[:, :-1]
    assert resting.sum() > 100 and np.abs(v[:, 1:][resting]).max() < 1e-4  # landed: stays, v = 0


def test_clear_errors(layout_and_scene, scene_cfg):
    layout, scene = layout_and_scene
    other = build_scene(scene_cfg, ["bag", "sphere"])
    x0 = torch.zeros((1, layout.num_vertices, 3))
    poses = torch.zeros((1, 3, len(layout.bodies), 7))
    with pytest.raises(ValueError, match="layout objects"):
        ContactProjectedPredictor(ConstantVelocity(), other).rollout(layout, x0, x0, poses, DT)
    with pytest.raises(ValueError, match=r"poses \(B, T>=2"):
        ContactProjectedPredictor(ConstantVelocity(), scene).rollout(layout, x0, x0, poses[:, :1], DT)
