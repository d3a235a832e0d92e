"""PiPER kinematics, geometry, IK and the Newton articulation (wc/scene/piper.py, robot_geometry.py, ik.py)."""

import math

import numpy as np
import pytest
import torch

from wc.rotations import quat_matrices, quat_matrices_torch
from wc.scene import piper as P
from wc.scene.ik import solve_tool_ik
from wc.scene.robot_geometry import LinkShape, link_surface_samples, piper_link_shapes, shape_surface_samples

IDENTITY_POSE = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
# tool pointing straight down (z = -Z), pad separation axis along world +Y, x = y cross z = -X
TOP_DOWN = torch.tensor([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return np.concatenate((rng.uniform(-0.5, 0.5, (n, 3)), quat), axis=1).astype(np.float32)


def random_joints(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    q = rng.uniform(P.JOINT_LIMITS[:, 0], P.JOINT_LIMITS[:, 1], (n, 6)).astype(np.float32)
    return q, rng.uniform(*P.OPENING_LIMITS_M, n).astype(np.float32)


@pytest.mark.slow
def test_fk_matches_newton_eval_fk():
    newton = pytest.importorskip("newton")
    import warp as wp

    from wc.sim.piper_newton import add_piper_articulation, piper_joint_q

    wp.config.quiet = True
    rng = np.random.default_rng(0)
    n = 20
    bases = random_poses(rng, n)
    q, opening = random_joints(rng, n)
    builder = newton.ModelBuilder()
    infos = [add_piper_articulation(builder, bases[i].tolist(), f"arm{i}_", with_shapes=True) for i in range(n)]
    model = builder.finalize(device="cpu")
    assert model.shape_count == n * len(P.LINK_NAMES)
    joint_q = model.joint_q.numpy()
    for i, info in enumerate(infos):
        joint_q[info["q_start"] : info["q_start"] + 8] = piper_joint_q(q[i], opening[i])
    state = model.state()
    newton.eval_fk(model, wp.array(joint_q, dtype=float, device="cpu"), model.joint_qd, state)
    body_q = state.body_q.numpy()

    ours = P.forward_kinematics_np(q, opening, bases)  # (n, 8, 7)
    for i, info in enumerate(infos):
        theirs = body_q[[info["bodies"][name] for name in P.LINK_NAMES]]
        np.testing.assert_allclose(body_q[info["bodies"]["base_link"]], bases[i], atol=1e-6)
        assert np.abs(ours[i, :, :3] - theirs[:, :3]).max() < 1e-5
        quat_diff = np.minimum(np.abs(ours[i, :, 3:] - theirs[:, 3:]), np.abs(ours[i, :, 3:] + theirs[:, 3:]))
        assert quat_diff.max() < 1e-5


def test_fingers_separate_and_pad_gap_equals_opening():
    openings = torch.linspace(0.0, 0.08, 9)
    q = torch.tensor(P.HOME_Q).expand(9, 6)
    poses = P.forward_kinematics(q, openings, IDENTITY_POSE)
    pads = P.pad_centres(poses)  # [9, 2, 3]
    gap = torch.linalg.vector_norm(pads[:, 0] - pads[:, 1], dim=-1) - 2 * P.PAD_HALF_EXTENTS_M[2]
    torch.testing.assert_close(gap, openings, atol=1e-6, rtol=0)
    assert torch.all(gap[1:] > gap[:-1])
    # finger_a on the +y side of the tool frame, finger_b on -y, the TCP halfway
    pos, rot, _ = P.tool_frame(q, openings, IDENTITY_POSE)
    side = torch.einsum("bi,bi->b", pads[:, 0] - pads[:, 1], rot[..., :, 1])
    torch.testing.assert_close(side, openings + 2 * P.PAD_HALF_EXTENTS_M[2], atol=1e-6, rtol=0)
    torch.testing.assert_close(pads.mean(dim=1), pos, atol=1e-6, rtol=0)
    assert P.gripper_to_finger_joints(0.06) == (0.03, -0.03)


def test_tool_z_points_along_the_fingers():
    rng = np.random.default_rng(1)
    q, opening = random_joints(rng, 16)
    poses = P.forward_kinematics(torch.from_numpy(q), torch.from_numpy(opening), IDENTITY_POSE)
    pos, rot, quat = P.tool_frame(torch.from_numpy(q), torch.from_numpy(opening), IDENTITY_POSE)
    approach = pos - poses[:, 5, :3]  # link6 origin (flange) -> TCP
    approach = approach / torch.linalg.vector_norm(approach, dim=-1, keepdim=True)
    torch.testing.assert_close(approach, rot[..., :, 2], atol=1e-5, rtol=0)
    torch.testing.assert_close(quat_matrices_torch(quat), rot, atol=1e-5, rtol=0)
    torch.testing.assert_close(P.tool_pose(torch.from_numpy(q), torch.from_numpy(opening), IDENTITY_POSE)[:, :3], pos)


def test_batch_shapes_numpy_and_gradients():
    q = torch.tensor(P.HOME_Q).expand(2, 3, 6).clone().requires_grad_()
    opening = torch.full((2, 3), 0.04)
    base = torch.from_numpy(random_poses(np.random.default_rng(2), 3))  # broadcasts over the leading 2
    poses = P.forward_kinematics(q, opening, base)
    assert poses.shape == (2, 3, 8, 7) and poses.dtype == torch.float32
    torch.testing.assert_close(poses[1, 2], P.forward_kinematics(q[1, 2], 0.04, base[2]))
    assert P.forward_kinematics(q[0, 0], torch.tensor(0.0), IDENTITY_POSE).shape == (8, 7)
    assert P.tool_pose(q, 0.0, IDENTITY_POSE).shape == (2, 3, 7)
    poses[..., 7, :3].sum().backward()
    assert torch.isfinite(q.grad).all() and q.grad.abs().sum() > 0
    np.testing.assert_allclose(
        P.forward_kinematics_np(P.HOME_Q, 0.0, IDENTITY_POSE.numpy()),
        P.forward_kinematics(torch.tensor(P.HOME_Q), 0.0, IDENTITY_POSE).numpy(),
    )


def test_home_and_limits():
    np.testing.assert_allclose(P.HOME_Q, [0, 1.57, -1.3485, 0, 0, 0])
    assert P.home_action(0.02).shape == (14,) and P.home_action(0.02)[6] == np.float32(0.02)
    q = torch.tensor([[-3.0, -0.5, 0.5, 2.0, -2.0, 4.0]])
    torch.testing.assert_close(P.clamp_to_limits(q), torch.tensor([[-2.618, 0.0, 0.0, 1.832, -1.22, 3.14]]))


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\[\.\.\., 6\]"):
        P.forward_kinematics(torch.zeros(5), 0.0, IDENTITY_POSE)
    with pytest.raises(ValueError, match=r"\[\.\.\., 7\]"):
        P.forward_kinematics(torch.zeros(6), 0.0, torch.zeros(6))
    with pytest.raises(ValueError, match=r"\[\.\.\., 14\]"):
        P.arm_poses_from_action(torch.zeros(3, 13), IDENTITY_POSE, IDENTITY_POSE)
    with pytest.raises(ValueError, match=r"\[B, 3\]"):
        solve_tool_ik(torch.zeros(2, 4), TOP_DOWN.expand(2, 3, 3), torch.zeros(2, 6), IDENTITY_POSE)


def test_arm_poses_from_action_places_arms_at_their_bases():
    left = torch.tensor([0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 1.0])
    yaw = math.pi / 2
    right = torch.tensor([0.0, -0.3, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
    action = torch.from_numpy(np.stack([P.home_action(0.0), P.home_action(0.05)]))
    poses = P.arm_poses_from_action(action, left, right)
    assert poses.shape == (2, 16, 7) and len(P.ARM_BODY_NAMES) == 16
    assert P.ARM_BODY_NAMES[0] == "left_link1" and P.ARM_BODY_NAMES[15] == "right_finger_b"
    torch.testing.assert_close(poses[:, 0, :3], torch.tensor([[0.0, 0.3, 0.123]] * 2))
    torch.testing.assert_close(poses[:, 8, :3], torch.tensor([[0.0, -0.3, 0.123]] * 2))
    torch.testing.assert_close(poses[:, 8:], P.forward_kinematics(action[:, 7:13], action[:, 13], right))
    # home reaches forward along the base x axis: +X for the left arm, +Y for the yawed right arm
    assert poses[0, 5, 0] > 0.3 and poses[0, 13, 1] > 0.0


@pytest.mark.parametrize(
    "base",
    [IDENTITY_POSE, torch.tensor([0.3, -0.2, 0.1, 0.0, 0.0, math.sin(0.4), math.cos(0.4)])],
    ids=["origin", "moved"],
)
def test_ik_converges_on_reachable_top_down_grasps(base):
    # relative to the base, in the base frame's axes
    targets_rel = torch.tensor([[0.0, 0.30, 0.0], [0.10, 0.25, 0.05], [0.30, 0.0, 0.0], [0.20, -0.20, -0.05]])
    base_rot = quat_matrices_torch(base[3:])
    targets = base[:3] + targets_rel @ base_rot.T
    rot = (base_rot @ TOP_DOWN).expand(4, 3, 3)
    q, pos_err, rot_err = solve_tool_ik(targets, rot, torch.tensor(P.HOME_Q).expand(4, 6), base, opening=0.03)
    assert pos_err.max() < 1e-3 and rot_err.max() < 1e-2, (pos_err, rot_err)
    torch.testing.assert_close(P.clamp_to_limits(q), q)
    pos, tool_rot, _ = P.tool_frame(q, 0.03, base)
    torch.testing.assert_close(pos, targets, atol=1e-3, rtol=0)
    torch.testing.assert_close(tool_rot, rot, atol=1e-2, rtol=0)


def test_ik_reports_unreachable_top_down_targets():
    # joint5 (+-1.22 rad) cannot tilt the tool 90 deg from a forearm at or above the horizontal,
    # so a straight-down tool is out of reach 0.15 m above the base at 0.3 m; IK says so via its errors
    targets = torch.tensor([[0.0, 0.30, 0.15], [0.10, 0.25, 0.25]])
    q, pos_err, rot_err = solve_tool_ik(targets, TOP_DOWN.expand(2, 3, 3), torch.tensor(P.HOME_Q).expand(2, 6),
                                        IDENTITY_POSE, iterations=60)
    assert torch.all((pos_err > 1e-3) | (rot_err > 1e-2))
    torch.testing.assert_close(P.clamp_to_limits(q), q)


def shape_frame(shape: LinkShape, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Link-frame points and normals in the primitive's own frame."""
    rot = quat_matrices(np.asarray(shape.local_quat_xyzw))
    return (points - shape.local_pos) @ rot, normals @ rot


def test_link_samples_lie_on_the_primitives_with_outward_normals():
    links = ("link5", "link6", "finger_a", "finger_b")
    spacing = 0.01
    samples = link_surface_samples(spacing, links)
    assert set(samples) == set(links)
    shapes = {s.link: s for s in piper_link_shapes()}
    assert set(shapes) == set(P.LINK_NAMES)
    for name, (points, normals) in samples.items():
        shape = shapes[name]
        assert points.dtype == np.float32 and normals.dtype == np.float32 and points.shape == normals.shape
        half = np.asarray(shape.size)
        p, n = shape_frame(shape, points, normals)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
        assert np.all(np.abs(p) <= half + 1e-6)
        np.testing.assert_allclose(np.max(np.abs(p) / half, axis=1), 1.0, atol=1e-5)  # on the surface
        assert np.all(np.max(np.abs(p + 1e-3 * n) / half, axis=1) > 1.0)  # outward
        assert np.all(np.max(np.abs(p - 1e-3 * n) / half, axis=1) < 1.0)
        # roughly uniform: every sample has a neighbour no further than the spacing
        d = np.linalg.norm(points[:, None] - points[None], axis=-1) + np.eye(len(points))
        assert d.min(axis=1).max() <= spacing + 1e-6
    finger_points = samples["finger_a"][0]
    assert finger_points[:, 1].max() == pytest.approx(P.PAD_ALONG_M + P.PAD_HALF_EXTENTS_M[1])
    # at least one point per face, even at a coarse spacing
    coarse = link_surface_samples(1.0, ["finger_a"])["finger_a"]
    assert len(coarse[0]) == 6 and len(np.unique(coarse[1], axis=0)) == 6


def test_capsule_samples():
    shape = LinkShape("link2", "capsule", (0.1, 0.0, 0.0), (0.0, math.sin(0.3), 0.0, math.cos(0.3)), (0.03, 0.1))
    points, normals = shape_surface_samples(shape, 0.01)
    p, n = shape_frame(shape, points, normals)
    axis_point = np.stack((np.zeros(len(p)), np.zeros(len(p)), np.clip(p[:, 2], -0.1, 0.1)), axis=1)
    np.testing.assert_allclose(np.linalg.norm(p - axis_point, axis=1), 0.03, atol=1e-6)
    np.testing.assert_allclose(p - axis_point, 0.03 * n, atol=1e-6)
    with pytest.raises(ValueError, match="unknown links"):
        link_surface_samples(0.01, ["gripper"])


def test_the_geometric_tool_jacobian_matches_autograd():
    """tool_jacobian's dp/dq and dR/dq against reverse-mode autograd of tool_frame, at random postures (float64)."""
    from torch.func import jacrev, vmap

    from wc.scene.ik import tool_jacobian

    gen = torch.Generator().manual_seed(3)
    q = torch.tensor(P.HOME_Q, dtype=torch.float64) + 0.5 * torch.randn(6, 6, generator=gen, dtype=torch.float64)
    base = torch.tensor([0.1, -0.2, 0.05, 0.0, 0.0, 0.3826834, 0.9238795], dtype=torch.float64)
    opening = torch.full((6,), 0.03, dtype=torch.float64)
    pos, rot, d_pos, d_rot = tool_jacobian(q, opening, base)

    def frame(qq: torch.Tensor, dd: torch.Tensor) -> torch.Tensor:
        p, r, _ = P.tool_frame(qq, dd, base)
        return torch.cat((p, r.reshape(9)))

    expected = vmap(jacrev(frame))(q, opening)  # [6, 12, 6]
    reference = vmap(frame)(q, opening)
    torch.testing.assert_close(torch.cat((pos, rot.reshape(6, 9)), dim=-1), reference)
    torch.testing.assert_close(d_pos, expected[:, :3], atol=1e-6, rtol=0)
    torch.testing.assert_close(d_rot.reshape(6, 9, 6), expected[:, 3:], atol=1e-6, rtol=0)
    assert expected.abs().amax() > 0.1  # the derivatives compared are not all near zero
