"""Contact projection: predicted cloth vertices that end up inside a collision body are put back on its surface.

A learnt simulator may under-react to contact (a small model lets the wrist sweep through a bag handle, or the
bag sink into the table). After each predicted step, every cloth vertex inside a collision body moves out of it
along the signed-distance gradient (the outward normal of the nearest face) of a body that contains it, onto the
surface of the union of the bodies: not beyond, and not into a neighbouring body (robot link boxes overlap at
the joints, pads touch the table). Of the containing bodies' normals, the one with the shortest way out of the
union is taken. Moved vertices get v = (x_next - x_prev) / dt, the velocity rule of the topology projection.

The bodies are the validation's own (wc.validate.predicates): the table box, the robot's link and finger-pad
boxes (`robot_boxes`), and the rigid objects, predicted (pose fitted to their rows) or held (posed by their link)
(`rigid_poses`, `convex_planes`). All are convex, so each is its face planes n . p <= offset in its own frame: a
point is inside when every plane holds, its depth is the nearest plane's distance (exact), and a ray meets it in
one interval. So a projected vertex passes the penetration check. Torch, batched over episodes, CPU or CUDA; only
the rigid-object poses are fitted on the CPU, as the check fits them.

Nothing here is bag-specific: it acts on the scene's cloth objects (`cloth_rows`) and whatever bodies it has.
`ContactProjectedPredictor` wraps any Predictor (wc.model.predictor) and steps it one frame at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from wc.model.predictor import Predictor
from wc.model.layout import SceneLayout
from wc.scene.scene import Scene
from wc.rotations import quat_matrices
from wc.validate.predicates import Episode, cloth_rows, convex_planes, rigid_poses, robot_boxes

BOX_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


@dataclass(frozen=True)
class Bodies:
    """Convex bodies with P face planes each: poses pos (B, K, 3), rot (B, K, 3, 3) (body -> world), outward
    unit normals (K, P, 3) and offsets (K, P) [m] in the body frame (inside: n . p_local <= offset)."""

    pos: Tensor
    rot: Tensor
    normals: Tensor
    offsets: Tensor

    def local(self, points: Tensor, batch: Tensor | None = None) -> Tensor:
        """Points (B, N, 3) in every body's frame (B, N, K, 3); with `batch` (M,), points (M, 3) of those
        episodes -> (M, K, 3)."""
        if batch is None:
            return torch.einsum("bnki,bkij->bnkj", points[:, :, None] - self.pos[:, None], self.rot)
        return torch.einsum("mki,mkij->mkj", points[:, None] - self.pos[batch], self.rot[batch])

    def depth(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Signed distance [m] (B, N, K) of points (B, N, 3) to each body, exact where negative (inside; a lower
        bound outside), and the world outward normal (B, N, K, 3) of its nearest face."""
        sd, face = (torch.einsum("bnkj,kpj->bnkp", self.local(points), self.normals) - self.offsets).max(dim=-1)
        normal = self.normals[torch.arange(self.normals.shape[0], device=face.device), face]  # (B, N, K, 3)
        return sd, torch.einsum("bkij,bnkj->bnki", self.rot, normal)

    def ray_intervals(self, start: Tensor, direction: Tensor, batch: Tensor) -> tuple[Tensor, Tensor]:
        """[t_in, t_out) (M, C, K) along rays start (M, 3) + t direction (M, C, 3) of episodes batch (M,) through
        every body (empty: t_in >= t_out)."""
        o = torch.einsum("kpj,mkj->mkp", self.normals, self.local(start, batch))  # n . o, (M, K, P)
        u = torch.einsum("mkij,mci->mckj", self.rot[batch], direction)  # direction in each body's frame
        a = torch.einsum("kpj,mckj->mckp", self.normals, u)  # n . u, (M, C, K, P)
        b = (self.offsets - o)[:, None]  # a t <= b on every plane
        ratio = b / torch.where(a == 0, torch.ones_like(a), a)
        inf = torch.full_like(a, float("inf"))
        t_in = torch.where(a < 0, ratio, -inf).amax(dim=-1)
        t_out = torch.where(a > 0, ratio, inf).amin(dim=-1)
        parallel_out = ((a == 0) & (b < 0)).any(dim=-1)
        return t_in, torch.where(parallel_out, t_in, t_out)


def ray_exit(t_in: Tensor, t_out: Tensor) -> Tensor:
    """Smallest t >= 0 (...,) outside every interval [t_in, t_out) (..., K): the ray's exit from their union."""
    t = torch.zeros(t_in.shape[:-1], dtype=t_in.dtype, device=t_in.device)
    for _ in range(t_in.shape[-1]):
        covered = (t_in <= t[..., None]) & (t[..., None] < t_out)
        if not bool(covered.any()):
            break
        t = torch.where(covered, t_out, t[..., None]).amax(dim=-1)
    return t


class ContactProjection:
    """Pushes a scene's cloth vertices out of its collision bodies (module docstring)."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.rows = torch.as_tensor(cloth_rows(scene), dtype=torch.long)
        self.has_rigid = bool(scene.held) or any(k == "rigid" for k in scene.object_kinds.values())
        self._planes: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def boxes(self, link_poses: np.ndarray, like: Tensor) -> Bodies:
        """The table (first) and robot boxes for link_poses (B, T, L, 7) in scene.link_names order: Bodies with
        pos (B, T, K, 3), rot (B, T, K, 3, 3) (index a frame with `frame_boxes`), as like's dtype and device."""
        B, T, L = link_poses.shape[:3]
        centre, quat, half = robot_boxes(self.scene, np.asarray(link_poses, np.float64).reshape(B * T, L, 7))
        table = np.broadcast_to(np.asarray(self.scene.table.center_m, np.float64), (B * T, 1, 3))
        pos = np.concatenate([table, centre], axis=1).reshape(B, T, -1, 3)
        rot = np.concatenate([np.broadcast_to(np.eye(3), (B * T, 1, 3, 3)), quat_matrices(quat)], axis=1)
        half = np.concatenate([np.asarray(self.scene.table.half_extents_m, np.float64)[None], half])  # (K, 3)
        normals = np.broadcast_to(BOX_NORMALS, (len(half), 6, 3))
        offsets = np.repeat(half, 2, axis=1)  # +x, -x, +y, -y, +z, -z faces

        def tensor(a: np.ndarray) -> Tensor:
            return torch.as_tensor(np.ascontiguousarray(a), dtype=like.dtype, device=like.device)

        return Bodies(tensor(pos), tensor(rot.reshape(B, T, -1, 3, 3)), tensor(normals), tensor(offsets))

    def rigid(self, x: Tensor, link_poses: np.ndarray) -> list[Bodies]:
        """The rigid bodies the cloth may touch, posed as the penetration check poses them (rigid_poses) from
        x (B, N, 3) and link_poses (B, L, 7); one Bodies (K = 1) each."""
        if not self.has_rigid:
            return []
        xs = np.nan_to_num(x.detach().double().cpu().numpy())  # a diverged episode must not break the pose fit
        ep = Episode(xs, xs, np.zeros((len(xs), 14)), np.asarray(link_poses), 1.0)  # rigid_poses reads x, link_poses
        out = []
        for name, mesh, pos, rot in rigid_poses(self.scene, ep):
            if name not in self._planes:
                self._planes[name] = convex_planes(mesh.vertices, mesh.faces, name)[:2]
            normals, offsets = self._planes[name]
            out.append(Bodies(*(torch.as_tensor(a, dtype=x.dtype, device=x.device)
                                for a in (pos[:, None], rot[:, None], normals[None], offsets[None]))))
        return out

    def push_out(self, points: Tensor, bodies: list[Bodies]) -> Tensor:
        """Points (B, N, 3) moved out of the union of `bodies` (see the module docstring); outside ones unchanged."""
        depths = [g.depth(points) for g in bodies]
        sd = torch.cat([d for d, _ in depths], dim=-1)  # (B, N, K)
        normal = torch.cat([n for _, n in depths], dim=-2)  # (B, N, K, 3)
        b, n = torch.nonzero(sd.amin(dim=-1) < 0, as_tuple=True)  # NaN (a diverged episode) compares False
        if len(b) == 0:
            return points
        start, candidates = points[b, n], normal[b, n]  # (M, 3), (M, C, 3): a containing body's nearest face
        t_in, t_out = zip(*(g.ray_intervals(start, candidates, b) for g in bodies))
        exit_t = ray_exit(torch.cat(t_in, dim=-1), torch.cat(t_out, dim=-1))  # (M, C)
        exit_t = torch.where(sd[b, n] < 0, exit_t, torch.full_like(exit_t, float("inf")))
        t, best = exit_t.min(dim=-1)
        out = points.clone()
        out[b, n] = start + t[:, None] * candidates[torch.arange(len(b), device=b.device), best]
        return out

    def project(self, x_prev: Tensor, x: Tensor, v: Tensor, dt: float, boxes: Bodies, frame: int,
                link_poses: np.ndarray, prev_link_poses: np.ndarray | None = None) -> tuple[Tensor, Tensor]:
        """Projected (x, v) (B, N, 3) of a predicted step x, v from x_prev (B, N, 3); `frame` indexes the boxes
        of the step, link_poses (B, L, 7) are its poses (for held objects); prev_link_poses (those at x_prev) are
        not used by the push alone."""
        rows = self.rows.to(x.device)
        if len(rows) == 0:
            return x, v
        frame_boxes = Bodies(boxes.pos[:, frame], boxes.rot[:, frame], boxes.normals, boxes.offsets)
        cloth = self.push_out(x[:, rows], [frame_boxes, *self.rigid(x, link_poses)])
        moved = (cloth != x[:, rows]).any(dim=-1, keepdim=True)
        x_out, v_out = x.clone(), v.clone()
        x_out[:, rows] = cloth
        v_out[:, rows] = torch.where(moved, (cloth - x_prev[:, rows]) / dt, v[:, rows])
        return x_out, v_out


class ContactProjectedPredictor:
    """Any Predictor followed, after every predicted frame, by the contact projection of `scene`.

    rollout(layout, x0, v0, poses, dt) as wc.model.predictor.Predictor: layout.objects must be the scene's
    objects and layout.bodies must hold every scene.link_names body; like WorldContact, the batch stops at the
    first step where an episode turns non-finite (the remaining frames stay NaN)."""

    def __init__(self, inner: Predictor, scene: Scene, projection: object | None = None) -> None:
        """projection: anything with `scene`, `boxes(link_poses, like)` and `project(...)` as ContactProjection (e.g.
        wc.expand.constraints.JointStepProjection); default the contact push alone."""
        self.inner = inner
        self.projection = projection if projection is not None else ContactProjection(scene)

    def _link_columns(self, layout: SceneLayout) -> list[int]:
        scene = self.projection.scene
        if tuple(layout.objects) != tuple(scene.objects):
            raise ValueError(f"contact projection: layout objects {layout.objects} are not the scene's "
                             f"{tuple(scene.objects)}")
        missing = [n for n in scene.link_names if n not in layout.bodies]
        if missing:
            raise ValueError(f"contact projection: the layout's bodies {layout.bodies} lack {missing}")
        return [layout.bodies.index(n) for n in scene.link_names]

    def rollout(self, layout: SceneLayout, x0: Tensor, v0: Tensor, poses: Tensor, dt: float
                ) -> tuple[Tensor, Tensor]:
        """Predicted x, v (B, T-1, N, 3) for frames 1..T-1 from x0, v0 (B, N, 3) under poses (B, T, P, 7)."""
        if x0.ndim != 3 or poses.ndim != 4 or poses.shape[0] != x0.shape[0] or poses.shape[1] < 2:
            raise ValueError(f"x0 must be (B, N, 3) and poses (B, T>=2, P, 7), got {tuple(x0.shape)} and "
                             f"{tuple(poses.shape)}")
        link_poses = poses[:, :, self._link_columns(layout)].detach().double().cpu().numpy()  # (B, T, L, 7)
        boxes = self.projection.boxes(link_poses, x0)
        steps = poses.shape[1] - 1
        xs = torch.full((x0.shape[0], steps, *x0.shape[1:]), float("nan"), dtype=x0.dtype, device=x0.device)
        vs = xs.clone()
        x, v = x0, v0
        for t in range(steps):
            px, pv = self.inner.rollout(layout, x, v, poses[:, t:t + 2], dt)
            x, v = self.projection.project(x, px[:, 0], pv[:, 0], dt, boxes, t + 1, link_poses[:, t + 1],
                                           link_poses[:, t])
            xs[:, t], vs[:, t] = x, v
            if not (torch.isfinite(x).all() and torch.isfinite(v).all()):
                break
        return xs, vs
