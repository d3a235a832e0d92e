"""Episode checks: a clean synthetic trajectory passes; each planted fault is caught by its predicate first."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from tests.conftest import load_params
from wc.rotations import quat_matrices
from wc.scene.scene import build_scene
from wc.validate import PREDICATES, ValidateConfig, first_failure
from wc.validate.failure_detail import failure_detail, penetration_detail
from wc.validate.predicates import (
    Episode, box_signed_distance, convex_depth, convex_planes, finger_pad_boxes, rigid_frames,
)
from wc.validate.self_intersection import crossing_edges, unique_edges

T = 12
DT = 0.04
CFG = ValidateConfig(
    max_speed_m_s=5.0, max_edge_strain=0.5, penetration_tol_m=0.003, self_intersection_every=1,
    release_opening_m=0.02, adhesion_radius_m=0.01, adhesion_window_s=0.2, adhesion_rise_m=0.02,
    workspace_min_m=(-0.5, -0.4, -0.02), workspace_max_m=(0.5, 0.4, 0.8), min_visible_fraction=0.9,
    val_per_task=0, test_per_task=1, split_seed=0,
)


@pytest.fixture(scope="module")
def scene(scene_cfg):
    return build_scene(scene_cfg)


@pytest.fixture()
def clean(scene):
    """The bag's rest mesh resting on the table, robot at home, for T frames."""
    rest = scene.objects["bag"].vertices
    x = np.repeat(rest[None], T, axis=0).copy()
    action = np.repeat(scene.home_action()[None], T, axis=0)
    return {"x": x, "v": np.zeros_like(x), "action": action, "link_poses": scene.link_poses(action)}


def episode(ep):
    return Episode(ep["x"], ep["v"], ep["action"], ep["link_poses"], DT)


def check(scene, ep, cfg=CFG):
    return first_failure(scene, ep["x"], ep["v"], ep["action"], ep["link_poses"], cfg, frame_dt_s=DT)


def bag_vertex(scene, key):
    """Index of a bag body vertex chosen by key(vertices) -> scores (argmin)."""
    return int(np.argmin(key(scene.objects["bag"].vertices)))


def test_clean_trajectory_passes(scene, clean):
    assert check(scene, clean) is None
    assert list(PREDICATES) == ["non_finite", "blow_up", "penetration", "self_intersection", "adhesion",
                                "workspace", "out_of_view"]


def test_nan(scene, clean):
    clean["x"][5, 17, 1] = np.nan
    assert check(scene, clean) == ("non_finite", 5)


def test_fast_vertex(scene, clean):
    clean["v"][6, 3] = (0.0, 0.0, 10.0)
    assert check(scene, clean) == ("blow_up", 6)


def test_over_stretched_edge(scene, clean):
    top = bag_vertex(scene, lambda p: -p[:, 2])
    clean["x"][4:, top, 2] += 0.05
    assert check(scene, clean) == ("blow_up", 4)


def test_bag_pushed_into_table(scene, clean):
    clean["x"][7:, :, 2] -= 0.02  # rigid shift: the bottom vertices sit 2 cm inside the table
    assert check(scene, clean) == ("penetration", 7)
    detail = penetration_detail(scene, episode(clean), CFG, 7)  # the report names the body and the depth
    assert detail["body"] == "table" and 0.015 < detail["depth_m"] < 0.025, detail


def test_shallow_table_contact_within_tolerance(scene, clean):
    clean["x"][7:, :, 2] -= 0.005
    assert check(scene, clean, dataclasses.replace(CFG, penetration_tol_m=0.01)) is None
    assert check(scene, clean) == ("penetration", 7)  # 5 mm is beyond the 3 mm default of these tests


def test_vertex_inside_finger_box(scene, clean):
    top = bag_vertex(scene, lambda p: -p[:, 2])
    k = scene.link_names.index("right_finger_a")
    centre, quat, _ = finger_pad_boxes(scene, clean["link_poses"], "right")
    clean["link_poses"][3:, k, :3] += clean["x"][0, top] - centre[0, 0]  # move the pad onto the vertex
    # the pad is 1 cm thick: a vertex at its centre is 5 mm deep, so the tolerance must stay below 5 mm
    assert check(scene, clean) == ("penetration", 3)
    detail = penetration_detail(scene, episode(clean), CFG, 3)
    assert detail["body"] == "right_finger_a" and detail["depth_m"] > CFG.penetration_tol_m, detail
    assert failure_detail(scene, episode(clean), CFG, "penetration", 3) == detail
    assert failure_detail(scene, episode(clean), CFG, "not_lifted", 3) == {}


def test_box_signed_distance_is_exact():
    q = np.array([0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)])  # 45 deg about z
    half = np.array([0.1, 0.2, 0.3])
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, 0.25]])
    d = box_signed_distance(pts, np.zeros(3), q, half)
    assert np.allclose(d, [-0.1, 0.2, -0.05])
    corner = np.array([0.1, 0.2, 0.3]) + np.array([0.03, 0.04, 0.0])  # box frame, 5 cm off a vertical edge
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    world = np.array([c * corner[0] - s * corner[1], s * corner[0] + c * corner[1], 0.3])
    assert np.isclose(box_signed_distance(world, np.zeros(3), q, half), 0.05)


def _push_through_back_panel(bag, x: np.ndarray, start: int) -> None:
    """From frame `start` on, a front-panel vertex at mid height sits beyond the back panel."""
    body, p = bag.groups["body"], bag.vertices
    score = np.abs(p[body, 0]) + np.abs(p[body, 2] - 0.06) + 10 * (p[body, 1] - p[:, 1].min())
    x[start:, int(body[np.argmin(score)]), 1] = p[:, 1].max() + 0.02


def test_crossing_triangles(scene, clean):
    bag = scene.objects["bag"]
    _push_through_back_panel(bag, clean["x"], 8)
    assert crossing_edges(clean["x"][8], bag.faces, unique_edges(bag.faces)).max() >= 0
    loose = dataclasses.replace(CFG, max_edge_strain=100.0)  # the push stretches its edges; judge crossings only
    assert check(scene, clean, loose) == ("self_intersection", 8)
    sparse = dataclasses.replace(loose, self_intersection_every=3)  # checked frames 0, 3, 6, 9
    assert check(scene, clean, sparse) == ("self_intersection", 9)


def test_shipped_params_check_every_frame():
    for path in ("params.yaml", "params/gpu.yaml"):
        assert load_params(file=path)["validate"]["self_intersection_every"] == 1, path


def _grip_handle_then_release(scene, clean):
    """Right pads 3 mm above the bag's top vertex, closed until frame 3, open from frame 3 on, and
    rising 1 cm per frame from then on."""
    top = bag_vertex(scene, lambda p: -p[:, 2])
    clean["action"][3:, 13] = 0.08
    centre, _, _ = finger_pad_boxes(scene, clean["link_poses"], "right")
    for f in ("finger_a", "finger_b"):
        k = scene.link_names.index(f"right_{f}")
        clean["link_poses"][:, k, 3:] = (0.0, 0.0, 0.0, 1.0)  # pads axis aligned: outward along world z
        j = 0 if f == "finger_a" else 1
        local = np.array([0.0, 0.025 if j == 0 else -0.025, 0.005])
        clean["link_poses"][:, k, :3] = clean["x"][0, top] + (0.0, 0.0, 0.008) - local
    rise = np.clip(np.arange(T) - 3, 0, None) * 0.01
    for f in ("finger_a", "finger_b"):
        clean["link_poses"][:, scene.link_names.index(f"right_{f}"), 2] += rise
    return rise


def test_bag_rising_with_open_gripper(scene, clean):
    rise = _grip_handle_then_release(scene, clean)
    clean["x"] += np.stack([np.zeros(T), np.zeros(T), rise], axis=1)[:, None, :].astype(np.float32)
    assert check(scene, clean) == ("adhesion", 3 + 5)  # window 0.2 s = 5 frames after the release


def test_bag_left_behind_by_open_gripper_passes(scene, clean):
    _grip_handle_then_release(scene, clean)
    assert check(scene, clean) is None


def test_bag_out_of_workspace(scene, clean):
    clean["x"][9:, :, 1] += 0.45  # sideways, away from the arms: past the 0.4 m workspace edge
    assert check(scene, clean) == ("workspace", 9)


def test_bag_out_of_view(scene, clean):
    clean["x"][10:, :, 0] += 0.8  # still on the table plane but beside the top camera's field of view
    wide = dataclasses.replace(CFG, workspace_min_m=(-2.0, -2.0, -0.02), workspace_max_m=(2.0, 2.0, 2.0))
    assert check(scene, clean, wide) == ("out_of_view", 10)


@pytest.mark.parametrize("field,value", [
    ("max_speed_m_s", 0.0), ("max_edge_strain", -0.1), ("penetration_tol_m", 0.0),
    ("self_intersection_every", 0), ("release_opening_m", -1.0), ("adhesion_radius_m", 0.0),
    ("adhesion_window_s", 0.0), ("adhesion_rise_m", -0.01), ("min_visible_fraction", 0.0),
    ("min_visible_fraction", 1.5), ("workspace_max_m", (-0.5, 0.4, 0.8)),
    ("val_per_task", -1), ("test_per_task", -2), ("split_seed", -1),
])
def test_config_rejects_bad_tolerances(field, value):
    CFG.validate()
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(CFG, **{field: value}).validate()


# -- rigid objects: predicted (fitted to their rows of x) and held (posed by link_poses) ---------------

HELD_POSE = (0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0)  # cube 10 cm out along right_link6's z, well above the bag


def yaw_matrix(deg):
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def with_rigid(scene, ep, name, centre, rot=np.eye(3), frames=slice(None)):
    """Episode `ep` (bag rows first) with the rigid object's rest mesh appended to x, posed at `centre`
    (3,) m with rotation `rot` in `frames` (beside the bag, see rigid_rest_centre, elsewhere)."""
    rest = scene.objects[name].vertices.astype(np.float64)
    rows = np.repeat((rest + rigid_rest_centre(scene, name))[None], T, axis=0)
    rows[frames] = rest @ rot.T + centre
    x = np.concatenate([ep["x"], rows.astype(np.float32)], axis=1)
    return {**ep, "x": x, "v": np.zeros_like(x)}


def rigid_rest_centre(scene, name):
    """Resting on the table, 2.5 cm to the +x side of the bag (of x = 0 without a bag)."""
    v = scene.objects[name].vertices
    bag_side = scene.objects["bag"].vertices[:, 0].max() if "bag" in scene.objects else 0.0
    return np.array([bag_side + 0.025 - v[:, 0].min(), 0.0, 0.0005 - v[:, 2].min()])


def side_vertex(scene):
    """A bag vertex on its +x side panel at mid height, and the outward direction there."""
    return bag_vertex(scene, lambda p: -p[:, 0] + np.abs(p[:, 2] - 0.05)), np.array([1.0, 0.0, 0.0])


def test_sphere_beside_bag_passes(scene_cfg, clean):
    scene = build_scene(scene_cfg, ["bag", "sphere"])
    ep = with_rigid(scene, clean, "sphere", rigid_rest_centre(scene, "sphere"))
    assert check(scene, ep) is None


def test_bag_vertex_inside_predicted_sphere(scene_cfg, clean):
    scene = build_scene(scene_cfg, ["bag", "sphere"])
    i, out = side_vertex(scene)
    r = scene_cfg.sphere.radius_m
    p = clean["x"][0, i].astype(np.float64)
    # 1 mm inside: within the 3 mm tolerance (the mesh's faces sit a little inside the true sphere)
    touching = with_rigid(scene, clean, "sphere", p + (r - 0.001) * out, yaw_matrix(30.0), slice(6, None))
    assert check(scene, touching) is None
    deep = with_rigid(scene, clean, "sphere", p + (r - 0.012) * out, yaw_matrix(30.0), slice(6, None))
    assert check(scene, deep) == ("penetration", 6)
    assert penetration_detail(scene, episode(deep), CFG, 6)["body"] == "sphere"


def test_bag_vertex_inside_held_cube(scene_cfg, clean):
    scene = build_scene(scene_cfg, ["bag"], held={"cube": ("right_link6", HELD_POSE)})
    clean["link_poses"] = scene.link_poses(clean["action"])
    assert check(scene, clean) is None
    i, out = side_vertex(scene)
    k = scene.link_names.index("held_cube")
    rot = quat_matrices(clean["link_poses"][0, k, 3:])
    # the cube (tilted with the wrist) moved so that the vertex is 1 cm inside its +x face
    local = np.array([scene_cfg.cube.half_extent_m - 0.01, 0.0, 0.0])
    clean["link_poses"][5:, k, :3] = clean["x"][0, i] - rot @ local
    assert check(scene, clean) == ("penetration", 5)


def test_handed_off_object_is_judged_by_its_rows_of_x(scene_cfg, clean):
    """An object both held and predicted (a hand-off) is checked where x puts it, not at its held pose."""
    scene = build_scene(scene_cfg, ["bag", "cube"], held={"cube": ("right_link6", HELD_POSE)})
    clean["link_poses"] = scene.link_poses(clean["action"])
    i, out = side_vertex(scene)
    k = scene.link_names.index("held_cube")
    clean["link_poses"][:, k, :3] = clean["x"][0, i]  # stale held pose right on the bag: ignored
    ep = with_rigid(scene, clean, "cube", rigid_rest_centre(scene, "cube"))
    assert check(scene, ep) is None
    h = scene_cfg.cube.half_extent_m
    deep = with_rigid(scene, clean, "cube", clean["x"][0, i] + (h - 0.01) * out, yaw_matrix(90.0), slice(8, None))
    assert check(scene, deep) == ("penetration", 8)


def test_scene_without_cloth(scene_cfg):
    """No bag: the cloth checks pass trivially; the checks of every predicted object still run."""
    scene = build_scene(scene_cfg, ["sphere"])
    rest = scene.objects["sphere"].vertices + rigid_rest_centre(scene, "sphere")
    x = np.repeat(rest[None], T, axis=0).astype(np.float32)
    action = np.repeat(scene.home_action()[None], T, axis=0)
    ep = {"x": x, "v": np.zeros_like(x), "action": action, "link_poses": scene.link_poses(action)}
    assert check(scene, ep) is None
    ep["x"][4, 0, 0] = np.inf
    assert check(scene, ep) == ("non_finite", 4)


def test_convex_depth_is_exact(scene_cfg):
    cube = build_scene(scene_cfg, ["cube"]).objects["cube"]
    h = scene_cfg.cube.half_extent_m
    planes = convex_planes(cube.vertices, cube.faces, "cube")
    assert len(planes[0]) == 6  # the grid's coplanar triangles share their face's plane
    rot = np.stack([yaw_matrix(a) @ yaw_matrix(90.0)[[2, 0, 1]] for a in (0.0, 40.0, 135.0)])  # (3, 3, 3)
    pos = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [-0.2, 0.1, 0.05]])
    local = np.array([[0.0, 0.0, 0.0], [h - 0.005, 0.0, 0.0], [h - 0.001, h - 0.002, 0.0], [h + 0.01, 0.0, 0.0]])
    for j, want in enumerate([h, 0.005, 0.001, -0.01]):
        world = np.einsum("tij,j->ti", rot, local[j])[:, None] + pos[:, None]
        assert np.allclose(convex_depth(world, pos, rot, planes), want)
    far = pos[:, None] + np.array([1.0, 0.0, 0.0])
    assert np.all(convex_depth(far, pos, rot, planes) == -np.inf)


def test_rigid_frames_recover_pose(scene_cfg):
    sphere = build_scene(scene_cfg, ["sphere"]).objects["sphere"]
    q = np.array([[0.0, 0.0, 0.0, 1.0], [0.3, -0.2, 0.5, 0.78]])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rot = quat_matrices(q)
    pos = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.3]])
    x = np.einsum("tij,nj->tni", rot, sphere.vertices.astype(np.float64)) + pos[:, None]
    fit_pos, fit_rot = rigid_frames(sphere.vertices, x)
    assert np.allclose(fit_pos, pos, atol=1e-6) and np.allclose(fit_rot, rot, atol=1e-6)


def test_convex_planes_rejects_non_convex(scene_cfg):
    cube = build_scene(scene_cfg, ["cube"]).objects["cube"]
    dented = cube.vertices.copy()
    top = int(np.argmin(np.abs(dented[:, 0]) + np.abs(dented[:, 1]) - dented[:, 2]))  # centre of the top face
    dented[top, 2] -= 0.01
    with pytest.raises(ValueError, match="convex"):
        convex_planes(dented, cube.faces, "dented cube")


def test_blow_up_says_which_criterion_fired(scene, clean):
    from wc.validate.failure_detail import blow_up_detail  # noqa: PLC0415
    from wc.validate.predicates import blow_up  # noqa: PLC0415

    fast = {k: np.array(a, copy=True) for k, a in clean.items()}
    fast["v"][4, 0] = [0.0, 0.0, CFG.max_speed_m_s + 1.0]
    ep = Episode(fast["x"], fast["v"], fast["action"], fast["link_poses"], 0.04)
    assert blow_up(scene, ep, CFG) == 4
    detail = blow_up_detail(scene, ep, CFG, 4)
    assert detail["criterion"] == "speed" and detail["max_speed_m_s"] > CFG.max_speed_m_s
    stretched = {k: np.array(a, copy=True) for k, a in clean.items()}
    stretched["x"][6:, 0] += [0.0, 0.0, 0.5]  # one vertex 50 cm off: its edges far beyond the strain limit
    ep = Episode(stretched["x"], stretched["v"], stretched["action"], stretched["link_poses"], 0.04)
    assert blow_up(scene, ep, CFG) == 6
    detail = blow_up_detail(scene, ep, CFG, 6)
    assert detail["criterion"] == "strain" and detail["max_edge_strain"] > CFG.max_edge_strain


def test_self_intersection_runs_on_the_configured_warp_device(scene, clean):
    """validate.device picks the warp device of the check: auto is the CPU here and finds the same crossing;
    a CUDA device this machine lacks is an error naming the key; an unknown name fails validation."""
    _push_through_back_panel(scene.objects["bag"], clean["x"], 5)
    loose = dataclasses.replace(CFG, max_edge_strain=100.0, device="auto")
    expected = ("self_intersection", 5)
    if wp.is_cuda_available():
        assert check(scene, clean, dataclasses.replace(loose, device="cuda:0")) == expected
    else:
        assert check(scene, clean, loose) == expected
        with pytest.raises(RuntimeError, match="validate.device is 'cuda'"):
            check(scene, clean, dataclasses.replace(loose, device="cuda"))
    with pytest.raises(ValueError, match="validate.device must be cpu, cuda"):
        dataclasses.replace(loose, device="tpu").validate()
