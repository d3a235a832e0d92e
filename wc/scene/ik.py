"""Batched inverse kinematics of the PiPER tool frame: damped least squares on the torch FK."""

from __future__ import annotations

import math

import torch

from wc.scene.piper import AXES, JOINT_LIMITS, chain_frames, clamp_to_limits, tool_from_frames


def tool_jacobian(q: torch.Tensor, opening: torch.Tensor | float, base_pose: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The TCP's position [B, 3] and rotation [B, 3, 3] (piper.tool_frame) and their derivatives by the six arm joints,
    from the chain's frames (a serial chain of revolute joints): dp/dq_i = a_i x (p - o_i) [B, 3, 6] and
    dR/dq_i = [a_i]x R [B, 3, 3, 6], with a_i and o_i joint i's world axis and origin. The geometric Jacobian: one
    forward pass, no autograd."""
    pos, rot, _ = chain_frames(q, opening, base_pose)  # [B, 8, 3], [B, 8, 3, 3]
    p, r = tool_from_frames(pos, rot)
    axes = (rot[:, :6] @ torch.as_tensor(AXES[:6], device=q.device, dtype=q.dtype)[..., None])[..., 0]  # [B, 6, 3]
    d_pos = torch.linalg.cross(axes, p[:, None] - pos[:, :6], dim=-1).transpose(1, 2)
    d_rot = torch.linalg.cross(axes[:, :, :, None].expand(-1, -1, -1, 3), r[:, None].expand(-1, 6, -1, -1), dim=2)
    return p, r, d_pos, d_rot.permute(0, 2, 3, 1)


def solve_tool_ik(
    target_pos: torch.Tensor,
    target_rot: torch.Tensor,
    q_init: torch.Tensor,
    base_pose: torch.Tensor,
    opening: torch.Tensor | float = 0.0,
    iterations: int = 100,
    damping: float = 0.02,
    rot_weight_m: float = 0.2,
    max_step_rad: float = 0.2,
    pos_tol_m: float = 1e-5,
    rot_tol_rad: float = 1e-4,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Joint angles q [B, 6] that put the TCP (piper.tool_pose) at target_pos [B, 3] (m), target_rot [B, 3, 3].

    target_rot's columns are the tool axes in the world (x, y = pad separation, z = approach).
    Each iteration takes a damped least-squares (Levenberg) step on the residual
    [p - p_t, rot_weight_m * (R - R_t) / sqrt(2)] (the rotation part is ~ rot_weight_m * angle),
    with the geometric Jacobian (tool_jacobian), each
    joint step capped at max_step_rad, then clamps q to the joint limits. Stops early once every sample is within both tolerances.
    base_pose: [7] or [B, 7]; opening (m): float or [B] (does not move the TCP).
    Returns q [B, 6], position error [B] (m) and rotation error [B] (rad); the latter from
    ||R - R_t||_F = 2 sqrt(2) sin(angle / 2), accurate at small angles unlike acos of the trace.
    """
    if target_pos.ndim != 2 or target_pos.shape[-1] != 3:
        raise ValueError(f"target_pos must have shape [B, 3], got {tuple(target_pos.shape)}")
    batch = target_pos.shape[0]
    if target_rot.shape != (batch, 3, 3):
        raise ValueError(f"target_rot must have shape [{batch}, 3, 3], got {tuple(target_rot.shape)}")
    if q_init.shape != (batch, 6):
        raise ValueError(f"q_init must have shape [{batch}, 6], got {tuple(q_init.shape)}")
    dev, dt = q_init.device, q_init.dtype
    target_pos, target_rot = target_pos.to(dev, dt), target_rot.to(dev, dt)
    base = torch.as_tensor(base_pose, device=dev, dtype=dt).expand(batch, 7)
    opening = torch.as_tensor(opening, device=dev, dtype=dt).expand(batch)
    scale = rot_weight_m / math.sqrt(2.0)

    def residual(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """r [B, 12] and dr/dq [B, 12, 6]."""
        pos, rot, d_pos, d_rot = tool_jacobian(q, opening, base)
        r = torch.cat((pos - target_pos, scale * (rot - target_rot).reshape(batch, 9)), dim=-1)
        return r, torch.cat((d_pos, scale * d_rot.reshape(batch, 9, 6)), dim=1)

    def errors(r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        chord = torch.linalg.vector_norm(r[:, 3:], dim=-1) / (scale * 2.0 * math.sqrt(2.0))
        return torch.linalg.vector_norm(r[:, :3], dim=-1), 2.0 * torch.asin(chord.clamp(max=1.0))

    eye = torch.eye(6, device=dev, dtype=dt)
    lower, upper = torch.as_tensor(JOINT_LIMITS, device=dev, dtype=dt).unbind(-1)
    q = clamp_to_limits(q_init.detach().clone())
    for _ in range(iterations):
        r, J = residual(q)
        pos_err, rot_err = errors(r)
        if bool(((pos_err < pos_tol_m) & (rot_err < rot_tol_rad)).all()):
            return q, pos_err, rot_err
        # a joint at a limit that the step pushes outward is frozen and the step re-solved without it,
        # so the other joints take over instead of the solver stalling against the limit
        free = torch.ones_like(q, dtype=torch.bool)
        for _ in range(6):
            Jf = J * free[:, None, :]
            Jt = Jf.transpose(1, 2)
            dq = -torch.linalg.solve(Jt @ Jf + damping**2 * eye, Jt @ r[..., None])[..., 0]
            blocked = free & (((q <= lower) & (dq < 0)) | ((q >= upper) & (dq > 0)))
            if not bool(blocked.any()):
                break
            free &= ~blocked
        q = clamp_to_limits(q + dq.clamp(-max_step_rad, max_step_rad))
    return (q, *errors(residual(q)[0]))
