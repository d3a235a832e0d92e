"""Scene assembly: only the objects a task needs, sample sets per body, held objects posed by their link."""

import numpy as np
import pytest

from wc.scene.cameras import camera_pose, intrinsics
from wc.scene.scene import build_scene
from wc.sim.kinematic import transform_points


def test_only_requested_objects(scene_cfg):
    scene = build_scene(scene_cfg, ["bag"])
    assert list(scene.objects) == ["bag"]
    both = build_scene(scene_cfg, ["sphere", "bag"])
    assert list(both.objects) == ["bag", "sphere"]  # fixed order, whatever the request order
    slices = both.vertex_slices()
    assert slices["sphere"].start == len(both.objects["bag"].vertices) == slices["bag"].stop
    with pytest.raises(ValueError, match="unknown object 'teapot'"):
        build_scene(scene_cfg, ["teapot"])


def test_samples_only_on_touching_links(scene_cfg):
    scene = build_scene(scene_cfg)
    bodies = {s.body for s in scene.samples}
    links = scene_cfg.robot.sampled_links
    assert bodies == {f"{side}_{link}" for side in ("left", "right") for link in links} | {"table"}
    assert all(s.body in scene.link_names + scene.env_names for s in scene.samples)
    tags = {s.tag for s in scene.samples}
    assert len(tags) == len(scene.samples)  # every sampled body has its own tag
    for s in scene.samples:
        np.testing.assert_allclose(np.linalg.norm(s.local_normals, axis=1), 1.0, atol=1e-5)


def test_held_object_follows_its_link(scene_cfg):
    local = [0.0, 0.0, 0.16, 0.0, 0.0, 0.0, 1.0]
    scene = build_scene(scene_cfg, ["bag"], held={"cube": ("right_link6", local)})
    assert scene.link_names[-1] == "held_cube" and "held_cube" in {s.body for s in scene.samples}
    rng = np.random.default_rng(0)
    actions = np.repeat(scene.home_action()[None], 3, axis=0)
    actions[:, 7:13] += rng.normal(scale=0.2, size=(3, 6))
    poses = scene.link_poses(actions)  # (3, 17, 7)
    link6 = poses[:, scene.link_names.index("right_link6")]
    held = poses[:, -1]
    np.testing.assert_allclose(held[:, :3], transform_points(link6, np.array([local[:3]]))[:, 0], atol=1e-6)
    np.testing.assert_allclose(np.abs(np.sum(held[:, 3:] * link6[:, 3:], axis=1)), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="unknown link"):
        build_scene(scene_cfg, ["bag"], held={"cube": ("right_elbow", local)})


def test_wrist_camera_rides_on_its_link(scene_cfg):
    scene = build_scene(scene_cfg)
    wrist, top = scene_cfg.cameras["wrist"], scene_cfg.cameras["top"]
    a = scene.home_action()
    b = a.copy()
    b[7] += 0.3  # turn the right arm's base joint
    eye_a, _ = camera_pose(wrist, scene.link_names, scene.link_poses(a))
    eye_b, _ = camera_pose(wrist, scene.link_names, scene.link_poses(b))
    assert np.linalg.norm(eye_a - eye_b) > 0.05
    eye, rot = camera_pose(top, scene.link_names, scene.link_poses(a))
    np.testing.assert_allclose(eye, top.position_m)
    view = rot @ np.array([0.0, 0.0, -1.0])  # OpenGL cameras look down their -z
    target = np.asarray(top.look_at_m) - eye
    np.testing.assert_allclose(view, target / np.linalg.norm(target), atol=1e-9)
    k = intrinsics(top)
    assert k[0, 2] == top.width / 2 and k[0, 0] > 0
    frames = scene.link_poses(np.stack([a, b]))  # many frames at once: each frame's pose
    for cam in (wrist, top):
        eyes, rots = camera_pose(cam, scene.link_names, frames)
        assert eyes.shape == (2, 3) and rots.shape == (2, 3, 3)
        for t in range(2):
            eye_t, rot_t = camera_pose(cam, scene.link_names, frames[t])
            np.testing.assert_allclose(eyes[t], eye_t, atol=1e-12)
            np.testing.assert_allclose(rots[t], rot_t, atol=1e-12)
