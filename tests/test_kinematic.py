"""Substep interpolation, body twists and rigid pose fitting."""

import numpy as np

from wc.rotations import quat_rotate
from wc.sim.kinematic import interpolate_actions, pose_twists, transform_points
from wc.sim.rigid_fit import rigid_pose_from_vertices


def _quat_z(angle: float) -> np.ndarray:
    return np.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)])


def test_interpolation_ends_at_next_action():
    a0, a1 = np.zeros(14, np.float32), np.arange(14, dtype=np.float32)
    sub = interpolate_actions(a0, a1, 20)
    assert sub.shape == (20, 14)
    np.testing.assert_allclose(sub[-1], a1)
    np.testing.assert_allclose(sub[9], a1 * 0.5)


def test_twist_of_a_known_motion():
    dt = 0.002
    p0 = np.array([0.1, 0.2, 0.3, *_quat_z(0.0)])
    p1 = np.array([0.1 + 0.004, 0.2, 0.3, *_quat_z(0.01)])
    twist = pose_twists(p0, p1, dt)
    np.testing.assert_allclose(twist[:3], [2.0, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(twist[3:], [0.0, 0.0, 5.0], atol=1e-3)


def test_rigid_fit_recovers_pose_and_twist():
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(40, 3))
    pose = np.array([0.3, -0.1, 0.5, *(_quat_z(0.7))])
    x = transform_points(pose, rest)
    lin, ang = np.array([0.1, 0.0, -0.2]), np.array([0.0, 0.5, 1.0])
    v = lin + np.cross(ang, x - pose[:3])
    fit, twist = rigid_pose_from_vertices(rest, x, v)
    np.testing.assert_allclose(transform_points(fit, rest), x, atol=1e-5)
    np.testing.assert_allclose(twist, np.concatenate([lin, ang]), atol=1e-5)
    np.testing.assert_allclose(quat_rotate(fit[3:], np.array([1.0, 0, 0])), quat_rotate(pose[3:], np.array([1.0, 0, 0])),
                               atol=1e-5)
