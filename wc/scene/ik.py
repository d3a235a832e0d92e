"""Batched inverse kinematics of the PiPER tool frame: damped least squares on the torch FK."""

from __future__ import annotations

import math

import torch
from torch.func import jacrev, vmap

from wc.scene.piper import JOINT_LIMITS, clamp_to_limits, tool_frame


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
    with the Jacobian from reverse-mode autograd (torch.func.jacrev, vmapped over the batch), each
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

    def residual(q, p_t, r_t, b, d):
        pos, rot, _ = tool_frame(q, d, b)
        r = torch.cat((pos - p_t, scale * (rot - r_t).reshape(9)))
        return r, r

    def errors(r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        chord = torch.linalg.vector_norm(r[:, 3:], dim=-1) / (scale * 2.0 * math.sqrt(2.0))
        return torch.linalg.vector_norm(r[:, :3], dim=-1), 2.0 * torch.asin(chord.clamp(max=1.0))

    jac = vmap(jacrev(residual, has_aux=True))
    args = (target_pos, target_rot, base, opening)
    eye = torch.eye(6, device=dev, dtype=dt)
    lower, upper = torch.as_tensor(JOINT_LIMITS, device=dev, dtype=dt).unbind(-1)
    q = clamp_to_limits(q_init.detach().clone())
    for _ in range(iterations):
        J, r = jac(q, *args)  # J [B, 12, 6], r [B, 12]
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
    return (q, *errors(vmap(residual)(q, *args)[0]))
