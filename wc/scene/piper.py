"""AgileX PiPER arm: kinematic chain (shared/reference/piper.md) and batched torch forward kinematics.

Poses are ``pos (3) + quat xyzw (4)`` float32, the Newton/warp convention. The chain table keeps
piper.md's quaternions as published (w x y z) and converts once below.

Finger and tool conventions, established by FK (see tests/test_piper.py):
- Both fingers sit at link6 (0, 0, 0.13503) when closed. Each finger slides along its own +z as
  the gripper opens (joint7 = +d/2 along +z of link7; joint8 = -d/2 along the -z axis of link8):
  finger_a moves to link6 +y, finger_b to link6 -y, so the published sign separates the pads.
- "Along the finger" (towards the fingertips, the approach direction) is link6 +z, which is
  finger_a +y and finger_b -y. Finger "outward" (away from the other finger) is each finger's +z.
- A pad is a 0.04 (x) x 0.06 (along) x 0.01 (outward) m box centred 0.025 m along the finger and
  0.005 m outward, so its inner face lies on the finger's sliding plane: the gap between the pads
  is exactly the opening d, and closed pads touch without overlapping.
- Tool centre point (TCP): the midpoint of the two pad centres, link6 (0, 0, 0.16003) for any
  opening. Its frame has link6's orientation: z = approach (along the fingers), y = pad separation
  axis (pointing from finger_b to finger_a), x = y cross z.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from wc.rotations import quat_matrices, quat_matrices_torch, quat_rotate_torch

LINK_NAMES: tuple[str, ...] = ("link1", "link2", "link3", "link4", "link5", "link6", "finger_a", "finger_b")
ARM_BODY_NAMES: tuple[str, ...] = tuple(f"{side}_{n}" for side in ("left", "right") for n in LINK_NAMES)
ACTION_DIM = 14  # [q_L (6), d_L, q_R (6), d_R]


@dataclass(frozen=True)
class JointSpec:
    """One joint of the chain: the child body's origin in its parent frame, axis in the child frame."""

    child: str
    parent: str  # "base_link" or an entry of LINK_NAMES
    kind: str  # "revolute" | "prismatic"
    origin_pos: tuple[float, float, float]  # m
    origin_quat_wxyz: tuple[float, float, float, float]  # as published in piper.md
    axis: tuple[float, float, float]
    lower: float  # rad or m
    upper: float


CHAIN: tuple[JointSpec, ...] = (
    JointSpec("link1", "base_link", "revolute", (0, 0, 0.123), (0.707105, 0, 0, -0.707108), (0, 0, 1), -2.618, 2.618),
    JointSpec("link2", "link1", "revolute", (0, 0, 0), (0.499998, 0.5, -0.500002, -0.5), (0, 0, 1), 0.0, 3.14),
    JointSpec(
        "link3", "link2", "revolute", (0.28358, 0.028726, 0), (0.998726, 0, 0, 0.0504536), (0, 0, 1), -2.697, 0.0
    ),
    JointSpec(
        "link4", "link3", "revolute", (-0.24221, 0.068514, 0), (0.544767, -0.544769, -0.450809, 0.450808), (0, 0, 1),
        -1.832, 1.832,
    ),
    JointSpec("link5", "link4", "revolute", (0, 0, 0), (0.707105, 0.707108, 0, 0), (0, 0, 1), -1.22, 1.22),
    JointSpec(
        "link6", "link5", "revolute", (0, 0.091, 0.0014165), (0, 0, -0.707105, -0.707108), (0, 0, 1), -3.14, 3.14
    ),
    JointSpec(
        "finger_a", "link6", "prismatic", (0, 0, 0.13503), (1.89468e-08, 1.89469e-08, 0.707108, 0.707105), (0, 0, 1),
        -0.05, 0.05,
    ),
    JointSpec(
        "finger_b", "link6", "prismatic", (0, 0, 0.13503), (1.89468e-08, -1.89469e-08, -0.707108, 0.707105), (0, 0, -1),
        -0.05, 0.05,
    ),
)

JOINT_LIMITS = np.array([[j.lower, j.upper] for j in CHAIN[:6]], dtype=np.float32)  # (6, 2) rad, joints 1..6
OPENING_LIMITS_M = (0.0, 0.08)  # gripper opening d between the pads
HOME_Q = np.array([0.0, 1.57, -1.3485, 0.0, 0.0, 0.0], dtype=np.float32)  # rad; gripper closed (d = 0)

PAD_HALF_EXTENTS_M = (0.02, 0.03, 0.005)  # finger frame: x, along-finger, outward (0.04 x 0.06 x 0.01 box)
PAD_ALONG_M = 0.025  # pad centre along the finger from the finger origin
# pad centres in the finger frames: along the finger is +y for finger_a and -y for finger_b; outward is +z
PAD_CENTRE_IN_FINGER_M = {
    "finger_a": (0.0, PAD_ALONG_M, PAD_HALF_EXTENTS_M[2]),
    "finger_b": (0.0, -PAD_ALONG_M, PAD_HALF_EXTENTS_M[2]),
}
FINGER_ORIGIN_IN_LINK6_M = CHAIN[6].origin_pos
TCP_IN_LINK6_M = (0.0, 0.0, FINGER_ORIGIN_IN_LINK6_M[2] + PAD_ALONG_M)  # along the fingers is link6 +z


def _quat_xyzw(wxyz: tuple[float, ...]) -> np.ndarray:
    q = np.array([wxyz[1], wxyz[2], wxyz[3], wxyz[0]], dtype=np.float64)
    return q / np.linalg.norm(q)  # published values have 6 digits; normalise so every consumer agrees


ORIGIN_POS = np.array([j.origin_pos for j in CHAIN], dtype=np.float32)  # (8, 3)
ORIGIN_QUAT_XYZW = np.stack([_quat_xyzw(j.origin_quat_wxyz) for j in CHAIN]).astype(np.float32)  # (8, 4)
AXES = np.array([j.axis for j in CHAIN], dtype=np.float32)  # (8, 3)
_PARENT_INDEX = tuple(-1 if j.parent == "base_link" else LINK_NAMES.index(j.parent) for j in CHAIN)


def transform_point(pose: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Map points p [..., 3] from a body frame to the world by poses [..., 7]."""
    return pose[..., :3] + quat_rotate_torch(pose[..., 3:], p)


def _check_last_dim(x: torch.Tensor, n: int, name: str) -> None:
    if x.ndim == 0 or x.shape[-1] != n:
        raise ValueError(f"{name} must have shape [..., {n}], got {tuple(x.shape)}")


def _right_multiply_matrix(b: np.ndarray) -> np.ndarray:
    """4x4 M with q * b == M @ q for xyzw quaternions (b need not be unit)."""
    bx, by, bz, bw = b
    return np.array([[bw, bz, -by, bx], [-bz, bw, bx, by], [by, -bx, bw, bz], [-bx, -by, -bz, bw]])


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


# Per joint, as row-vector operators so a step is a few batched matmuls (few ops keep autograd cheap):
# quat * origin_quat = quat @ _ORIGIN_QMAT_T; quat * (axis sin(v/2), cos(v/2)) = cos quat + sin quat @ _AXIS_QMAT_T;
# rot @ R_axis(v) = rot + sin(v) rot @ K + (1 - cos(v)) rot @ K^2 (Rodrigues).
_ORIGIN_ROT = np.stack([quat_matrices(q) for q in ORIGIN_QUAT_XYZW.astype(np.float64)])
_ORIGIN_QMAT_T = np.stack([_right_multiply_matrix(q).T for q in ORIGIN_QUAT_XYZW.astype(np.float64)])
_AXIS_QMAT_T = np.stack([_right_multiply_matrix(np.append(a, 0.0)).T for a in AXES.astype(np.float64)])
_AXIS_K = np.stack([_skew(a) for a in AXES.astype(np.float64)])


@lru_cache(maxsize=None)
def _chain_tensors(device: torch.device, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    arrays = dict(
        origin_pos=ORIGIN_POS, origin_rot=_ORIGIN_ROT, origin_qmat_t=_ORIGIN_QMAT_T, axis=AXES,
        axis_qmat_t=_AXIS_QMAT_T, k=_AXIS_K, kk=_AXIS_K @ _AXIS_K,
    )
    return {k: torch.as_tensor(v, device=device, dtype=dtype) for k, v in arrays.items()}


# ---- kinematics ----

def gripper_to_finger_joints(opening_m):
    """Finger joint values (joint7, joint8) in m for a gripper opening d in m (float, array or tensor).

    piper.md's published convention (d/2, -d/2) is correct: FK shows it separates the pads.
    """
    return 0.5 * opening_m, -0.5 * opening_m


def clamp_to_limits(q: torch.Tensor) -> torch.Tensor:
    """Clamp arm joint angles [..., 6] (rad) to JOINT_LIMITS."""
    _check_last_dim(q, 6, "q")
    lim = torch.as_tensor(JOINT_LIMITS, device=q.device, dtype=q.dtype)
    return torch.clamp(q, lim[:, 0], lim[:, 1])


def chain_frames(
    q: torch.Tensor, opening: torch.Tensor | float, base_pose: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World frames of LINK_NAMES: positions [..., 8, 3] (m), rotations [..., 8, 3, 3], quats xyzw [..., 8, 4]."""
    _check_last_dim(q, 6, "q")
    _check_last_dim(base_pose, 7, "base_pose")
    batch = q.shape[:-1]
    c = _chain_tensors(q.device, q.dtype)
    opening = torch.as_tensor(opening, device=q.device, dtype=q.dtype).expand(batch)
    j7, j8 = gripper_to_finger_joints(opening)
    values = torch.cat((q, j7[..., None], j8[..., None]), dim=-1)[..., None]  # [..., 8, 1]
    base_pose = torch.as_tensor(base_pose, device=q.device, dtype=q.dtype)
    base_quat = base_pose[..., 3:].expand(*batch, 4)
    base = (base_pose[..., :3].expand(*batch, 3), quat_matrices_torch(base_quat), base_quat)

    frames: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    for i, spec in enumerate(CHAIN):
        p_pos, p_rot, p_quat = base if _PARENT_INDEX[i] < 0 else frames[_PARENT_INDEX[i]]
        pos = p_pos + p_rot @ c["origin_pos"][i]
        rot = p_rot @ c["origin_rot"][i]
        quat = p_quat @ c["origin_qmat_t"][i]
        v = values[..., i, :]  # [..., 1]
        if spec.kind == "revolute":
            s, co = torch.sin(v)[..., None], torch.cos(v)[..., None]
            rot = rot + s * (rot @ c["k"][i]) + (1.0 - co) * (rot @ c["kk"][i])
            quat = torch.cos(0.5 * v) * quat + torch.sin(0.5 * v) * (quat @ c["axis_qmat_t"][i])
        else:
            pos = pos + (rot @ c["axis"][i]) * v
        frames.append((pos, rot, quat))
    pos, rot, quat = zip(*frames)
    return torch.stack(pos, dim=-2), torch.stack(rot, dim=-3), torch.stack(quat, dim=-2)


def forward_kinematics(q: torch.Tensor, opening: torch.Tensor | float, base_pose: torch.Tensor) -> torch.Tensor:
    """World poses [..., 8, 7] of LINK_NAMES for joints q [..., 6] (rad) and gripper opening [...] (m).

    base_pose: the base_link pose, [7] or broadcastable [..., 7]. Differentiable; no clamping;
    computed in q's dtype and device (float32 expected).
    """
    pos, _, quat = chain_frames(q, opening, base_pose)
    return torch.cat((pos, quat), dim=-1)


def forward_kinematics_np(q: np.ndarray, opening: np.ndarray | float, base_pose: np.ndarray) -> np.ndarray:
    """numpy wrapper of forward_kinematics: float32 poses [..., 8, 7]."""
    q, opening, base_pose = (torch.as_tensor(np.asarray(a, dtype=np.float32)) for a in (q, opening, base_pose))
    with torch.no_grad():
        return forward_kinematics(q, opening, base_pose).numpy()


def tool_frame(
    q: torch.Tensor, opening: torch.Tensor | float, base_pose: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """TCP world position [..., 3] (m), rotation [..., 3, 3] and quat xyzw [..., 4]; see tool_pose."""
    pos, rot, quat = chain_frames(q, opening, base_pose)
    return (*tool_from_frames(pos, rot), quat[..., LINK_NAMES.index("link6"), :])


def tool_from_frames(pos: torch.Tensor, rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP world position [..., 3] and rotation [..., 3, 3] from chain_frames' positions and rotations."""
    i = LINK_NAMES.index("link6")
    tcp = torch.as_tensor(TCP_IN_LINK6_M, device=pos.device, dtype=pos.dtype)
    return pos[..., i, :] + rot[..., i, :, :] @ tcp, rot[..., i, :, :]


def tool_pose(q: torch.Tensor, opening: torch.Tensor | float, base_pose: torch.Tensor) -> torch.Tensor:
    """TCP world pose [..., 7]: midpoint of the pad centres, z = approach, y = pad separation axis."""
    pos, _, quat = tool_frame(q, opening, base_pose)
    return torch.cat((pos, quat), dim=-1)


def pad_centres(poses: torch.Tensor) -> torch.Tensor:
    """World pad centres [..., 2, 3] (finger_a, finger_b) from FK poses [..., 8, 7]."""
    local = torch.tensor(
        [PAD_CENTRE_IN_FINGER_M["finger_a"], PAD_CENTRE_IN_FINGER_M["finger_b"]], device=poses.device, dtype=poses.dtype
    )
    return transform_point(poses[..., 6:8, :], local.expand(*poses.shape[:-2], 2, 3))


def arm_poses_from_action(action: torch.Tensor, left_base: torch.Tensor, right_base: torch.Tensor) -> torch.Tensor:
    """Poses [..., 16, 7] of ARM_BODY_NAMES from actions [..., 14] = [q_L (6), d_L, q_R (6), d_R]."""
    _check_last_dim(action, ACTION_DIM, "action")
    left = forward_kinematics(action[..., 0:6], action[..., 6], left_base)
    right = forward_kinematics(action[..., 7:13], action[..., 13], right_base)
    return torch.cat((left, right), dim=-2)


def home_action(opening_m: float = 0.0) -> np.ndarray:
    """Both arms at HOME_Q with the given gripper opening: float32 [14]."""
    d = np.float32(opening_m)
    return np.concatenate((HOME_Q, [d], HOME_Q, [d])).astype(np.float32)

