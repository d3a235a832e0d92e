"""One PiPER arm as a Newton articulation, with the joint origins and axes of wc.scene.piper."""

from __future__ import annotations

from collections.abc import Sequence

import newton
import numpy as np
import warp as wp

from wc.scene.piper import AXES, CHAIN, ORIGIN_POS, ORIGIN_QUAT_XYZW, gripper_to_finger_joints
from wc.scene.robot_geometry import piper_link_shapes


def add_piper_articulation(
    builder: newton.ModelBuilder,
    base_pose: Sequence[float],
    label_prefix: str,
    with_shapes: bool = False,
    shape_cfg: newton.ModelBuilder.ShapeConfig | None = None,
) -> dict:
    """Add base_link (fixed to the world at base_pose: pos 3 + quat xyzw 4) and the 8 moving bodies.

    Joints: fixed base, revolute joint1..6, prismatic joint7 (finger_a) and joint8 (finger_b); each
    joint's parent_xform is the chain origin, its axis the chain axis, limits from the chain.
    with_shapes adds piper_link_shapes() (shape_cfg or the builder default).
    Returns {"bodies": {name: body index} incl. "base_link", "joints": [joint indices],
    "articulation": index, "q_start": index of joint1 in joint_q (the arm's 8 coordinates follow)}.
    """
    if len(base_pose) != 7:
        raise ValueError(f"base_pose must have shape [7] (pos 3 + quat xyzw 4), got {len(base_pose)} values")
    base_xform = wp.transform(wp.vec3(*base_pose[:3]), wp.quat(*base_pose[3:]))
    bodies = {"base_link": builder.add_link(xform=base_xform, label=f"{label_prefix}base_link")}
    joints = [builder.add_joint_fixed(-1, bodies["base_link"], parent_xform=base_xform, label=f"{label_prefix}base")]
    for i, spec in enumerate(CHAIN):
        child = builder.add_link(label=f"{label_prefix}{spec.child}")
        bodies[spec.child] = child
        add_joint = builder.add_joint_revolute if spec.kind == "revolute" else builder.add_joint_prismatic
        joints.append(
            add_joint(
                bodies[spec.parent],
                child,
                parent_xform=wp.transform(wp.vec3(*ORIGIN_POS[i]), wp.quat(*ORIGIN_QUAT_XYZW[i])),
                axis=wp.vec3(*AXES[i]),
                limit_lower=spec.lower,
                limit_upper=spec.upper,
                label=f"{label_prefix}joint{i + 1}",
            )
        )
    articulation = builder.articulation_count
    builder.add_articulation(joints, label=f"{label_prefix}piper")
    if with_shapes:
        for s in piper_link_shapes():
            body, xform = bodies[s.link], wp.transform(wp.vec3(*s.local_pos), wp.quat(*s.local_quat_xyzw))
            if s.kind == "box":
                builder.add_shape_box(body, xform=xform, hx=s.size[0], hy=s.size[1], hz=s.size[2], cfg=shape_cfg)
            else:
                builder.add_shape_capsule(body, xform=xform, radius=s.size[0], half_height=s.size[1], cfg=shape_cfg)
    q_start = builder.joint_q_start[joints[1]]
    return {"bodies": bodies, "joints": joints, "articulation": articulation, "q_start": q_start}


def piper_joint_q(q: np.ndarray, opening_m: float) -> np.ndarray:
    """The arm's 8 Newton joint coordinates [q1..q6 (rad), joint7, joint8 (m)] as float32."""
    j7, j8 = gripper_to_finger_joints(float(opening_m))
    return np.concatenate((np.asarray(q, dtype=np.float32).reshape(6), [j7, j8])).astype(np.float32)

