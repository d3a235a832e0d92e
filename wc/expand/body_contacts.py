"""The scene's collision bodies posed on the device, and cloth pushed out of them with static shapes: the contact part
of the fast expansion path (wc.expand.fixed_projection). The reference, with host syncs and dynamic shapes, is
wc.expand.contact; both use its `Bodies` (convex bodies as face planes) and the same rule: a vertex inside the union
of the bodies goes along the nearest face normal of a body containing it to where that ray leaves the union.

The bodies are the validation's own: the table box, the robot's link and finger-pad boxes (wc.validate.predicates
`robot_box_shapes`), held objects posed by their link column, and predicted rigid objects posed by a rigid fit to
their rows (Horn's quaternion, by repeated squaring: no eigen-solver, no host sync). Nothing is bag-specific.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from wc.expand.contact import BOX_NORMALS, Bodies
from wc.expand.cloth_elements import host_checks
from wc.rotations import quat_matrices_torch, quat_multiply_torch, quat_rotate_torch
from wc.validate.predicates import cloth_rows, convex_planes, robot_box_shapes

SQUARINGS = 12  # repeated squarings of Horn's matrix: the top eigenvector dominates as lambda^(2^12)


def horn_rotation(rest: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
    """Best rigid fit x ~ rest @ R^T + pos of rest points (n, 3) to states x (B, n, 3): pos (B, 3) of the rest origin and
    R (B, 3, 3) (Horn 1987: the unit quaternion maximising the fit is the top eigenvector of a symmetric 4 x 4)."""
    rc, xc = rest.mean(dim=0), x.mean(dim=1)
    s = torch.einsum("ni,bnj->bij", rest - rc, x - xc[:, None])  # S_ab = sum rest_a x_b
    sxx, sxy, sxz = s[:, 0, 0], s[:, 0, 1], s[:, 0, 2]
    syx, syy, syz = s[:, 1, 0], s[:, 1, 1], s[:, 1, 2]
    szx, szy, szz = s[:, 2, 0], s[:, 2, 1], s[:, 2, 2]
    n = torch.stack([
        torch.stack([sxx + syy + szz, syz - szy, szx - sxz, sxy - syx], -1),
        torch.stack([syz - szy, sxx - syy - szz, sxy + syx, szx + sxz], -1),
        torch.stack([szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy], -1),
        torch.stack([sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz], -1)], -2)  # (B, 4, 4), (w, x, y, z)
    shift = n.abs().sum(dim=(-1, -2)).clamp_min(1e-30)  # >= the spectral radius: N + shift I is positive semidefinite
    a = (n + shift[:, None, None] * torch.eye(4, dtype=x.dtype, device=x.device)) / (2 * shift[:, None, None])
    for _ in range(SQUARINGS):
        a = a @ a
        a = a / a.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1e-30)
    column = a.norm(dim=-2).argmax(dim=-1)  # a column with weight on the top eigenvector
    q = a.gather(-1, column[:, None, None].expand(-1, 4, 1))[..., 0]
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    rot = quat_matrices_torch(torch.cat([q[:, 1:], q[:, :1]], dim=-1))  # xyzw
    return xc - torch.einsum("bij,j->bi", rot, rc), rot


def union_exit(t_in: Tensor, t_out: Tensor) -> Tensor:
    """Smallest t >= 0 (...,) outside every interval [t_in, t_out) (..., K), in K fixed passes (each pass jumps past
    the intervals covering t; K passes cross any chain of K overlapping bodies)."""
    t = torch.zeros(t_in.shape[:-1], dtype=t_in.dtype, device=t_in.device)
    for _ in range(t_in.shape[-1]):
        covered = (t_in <= t[..., None]) & (t[..., None] < t_out)
        if host_checks(t) and not bool(covered.any()):
            break
        t = torch.where(covered, t_out, t[..., None]).amax(dim=-1)
    return t


def push_out(points: Tensor, bodies: list[Bodies], candidates: int = 2) -> tuple[Tensor, Tensor]:
    """Points (B, n, 3) moved out of the union of the bodies, and (B, n) bool which moved. Of the bodies containing a
    point, the `candidates` shallowest (nearest face) offer their face normal; the shortest exit among them is taken.
    On CUDA every point is evaluated (static shapes); the CPU evaluates the points inside a body only."""
    bsz, n = points.shape[:2]
    depths = [g.depth(points) for g in bodies]
    sd = torch.cat([d for d, _ in depths], dim=-1).reshape(bsz * n, -1)  # (B n, K)
    normal = torch.cat([nrm for _, nrm in depths], dim=-2).reshape(bsz * n, -1, 3)
    c = min(candidates, sd.shape[-1])
    key = torch.where(sd < 0, sd, torch.full_like(sd, -float("inf")))  # NaN (a diverged episode) is not inside
    top, body = key.topk(c, dim=-1)  # the shallowest containing bodies
    inside = top[:, 0] > -float("inf")
    idx = inside.nonzero()[:, 0] if host_checks(points) else torch.arange(bsz * n, device=points.device)
    start = points.reshape(-1, 3)[idx]
    direction = normal[idx].gather(1, body[idx][..., None].expand(-1, -1, 3))  # (M, C, 3)
    t_in, t_out = zip(*(g.ray_intervals(start, direction, idx // n) for g in bodies))
    exit_t = union_exit(torch.cat(t_in, dim=-1), torch.cat(t_out, dim=-1))  # (M, C)
    exit_t = torch.where(top[idx] > -float("inf"), exit_t, torch.full_like(exit_t, float("inf")))
    t, best = exit_t.min(dim=-1)
    ok = torch.isfinite(t)
    step = torch.where(ok, t, torch.zeros_like(t))[:, None] * direction[torch.arange(len(idx), device=idx.device), best]
    out = points.reshape(-1, 3).clone()
    out[idx] = start + step
    moved = torch.zeros(bsz * n, dtype=torch.bool, device=points.device)
    moved[idx] = ok
    return out.view_as(points), moved.view(bsz, n)


class DeviceBodies:
    """The scene's collision bodies (module docstring) as device tensors, posed per frame by `pose`."""

    def __init__(self, scene, device: torch.device) -> None:  # noqa: ANN001 - wc.scene.scene.Scene
        def t(a: np.ndarray, dtype: torch.dtype = torch.float32) -> Tensor:
            return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

        shapes = robot_box_shapes(scene)
        self.box_columns = t(np.array([k for k, _ in shapes], np.int64), torch.long)
        self.box_local_pos = t(np.array([s.local_pos for _, s in shapes], np.float64).reshape(-1, 3))
        self.box_local_quat = t(np.array([s.local_quat_xyzw for _, s in shapes], np.float64).reshape(-1, 4))
        half = np.concatenate([np.asarray(scene.table.half_extents_m, np.float64)[None],
                               np.array([s.size for _, s in shapes], np.float64).reshape(-1, 3)])
        self.box_normals = t(np.broadcast_to(BOX_NORMALS, (len(half), 6, 3)))
        self.box_offsets = t(np.repeat(half, 2, axis=1))  # +x, -x, +y, -y, +z, -z faces
        self.table_pos = t(np.asarray(scene.table.center_m, np.float64))
        self.held = []  # (link column, normals (1, P, 3), offsets (1, P))
        for body, held in scene.held.items():
            if body.removeprefix("held_") in scene.objects:
                continue  # a hand-off: its rows of x follow the held pose, the rigid fit covers it
            normals, offsets, _ = convex_planes(held.mesh.vertices, held.mesh.faces, body)
            self.held.append((scene.link_names.index(body), t(normals[None]), t(offsets[None])))
        self.rigid = []  # (rows, rest vertices (n, 3), normals (1, P, 3), offsets (1, P))
        slices = scene.vertex_slices()
        for name, mesh in scene.objects.items():
            if scene.object_kinds[name] == "rigid":
                normals, offsets, _ = convex_planes(mesh.vertices, mesh.faces, name)
                rows = t(np.arange(slices[name].start, slices[name].stop), torch.long)
                self.rigid.append((rows, t(mesh.vertices), t(normals[None]), t(offsets[None])))
        self.cloth = t(cloth_rows(scene), torch.long)

    def pose(self, link_poses: Tensor, x: Tensor) -> list[Bodies]:
        """The bodies at link poses (B, L, 7) (scene.link_names order) with the predicted state x (B, N, 3)."""
        body = link_poses[:, self.box_columns]  # (B, K, 7)
        centre = body[..., :3] + quat_rotate_torch(body[..., 3:], self.box_local_pos.expand_as(body[..., :3]))
        quat = quat_multiply_torch(body[..., 3:], self.box_local_quat.expand_as(body[..., 3:]))
        b = link_poses.shape[0]
        table_rot = torch.eye(3, dtype=x.dtype, device=x.device).expand(b, 1, 3, 3)
        boxes = Bodies(torch.cat([self.table_pos.expand(b, 1, 3), centre], dim=1),
                       torch.cat([table_rot, quat_matrices_torch(quat)], dim=1), self.box_normals, self.box_offsets)
        out = [boxes]
        for column, normals, offsets in self.held:
            pose = link_poses[:, column]
            out.append(Bodies(pose[:, None, :3], quat_matrices_torch(pose[:, 3:])[:, None], normals, offsets))
        for rows, rest, normals, offsets in self.rigid:
            pos, rot = horn_rotation(rest, torch.nan_to_num(x[:, rows]))
            out.append(Bodies(pos[:, None], rot[:, None], normals, offsets))
        return out

    def depth(self, x: Tensor, bodies: list[Bodies]) -> Tensor:
        """(B,) deepest penetration [m] (>= 0) of the cloth rows of x (B, N, 3) into the bodies."""
        if len(self.cloth) == 0:
            return x.new_zeros(x.shape[0])
        sd = torch.cat([g.depth(x[:, self.cloth])[0] for g in bodies], dim=-1)
        return (-sd.amin(dim=-1)).clamp_min(0.0).amax(dim=-1)
