"""The source data's checks on generated frames as they are produced, on the device (the fast expansion path).

Per frame and episode, the predicates of wc.validate.predicates that look at one frame: non_finite, blow_up (vertex
speed, rest-edge strain over every object), penetration (cloth deeper than the tolerance in the table, a robot box or
a rigid object: the projection's own bodies, wc.expand.body_contacts), self_intersection (the crossing the rollback
could not undo: the same BVH test as the validate stage's, wc.validate.cloth_bvh) and workspace. `FirstFailures`
keeps the first failing frame of each, on the device; the multi-frame checks (adhesion, the camera view) and the task's
own verdict run on the finished episode (wc.expand.verdicts). Nothing is bag-specific.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from wc.expand.body_contacts import DeviceBodies
from wc.expand.contact import Bodies
from wc.validate.config import ValidateConfig
from wc.validate.self_intersection import unique_edges

FRAME_CHECKS = ("non_finite", "blow_up", "penetration", "self_intersection", "workspace")
NEVER = 1 << 30  # first failing frame of a check that has not failed


class FrameChecks:
    """The one-frame predicates of a scene for a batch of frames (module docstring)."""

    def __init__(self, scene, cfg: ValidateConfig, bodies: DeviceBodies, device: torch.device) -> None:  # noqa: ANN001
        self.cfg, self.bodies = cfg, bodies
        slices = scene.vertex_slices()
        edges, rest = [], []
        for name, mesh in scene.objects.items():
            e = unique_edges(mesh.faces).astype(np.int64)
            edges.append(e + slices[name].start)
            rest.append(np.linalg.norm(mesh.vertices[e[:, 0]] - mesh.vertices[e[:, 1]], axis=-1))
        self.edges = torch.as_tensor(np.concatenate(edges), device=device)
        self.rest = torch.as_tensor(np.maximum(np.concatenate(rest), 1e-12), dtype=torch.float32, device=device)
        self.low = torch.as_tensor(cfg.workspace_min_m, dtype=torch.float32, device=device)
        self.high = torch.as_tensor(cfg.workspace_max_m, dtype=torch.float32, device=device)

    def __call__(self, x: Tensor, v: Tensor, link_poses: Tensor, crossing: Tensor,
                 stats: dict[str, Tensor] | None = None) -> Tensor:
        """(B, 5) bool: which of FRAME_CHECKS fail on frames x, v (B, N, 3) at link poses (B, L, 7), given the
        projection's crossing flags (B,); the deepest penetration goes into stats["max_depth_after_m"] if given."""
        cfg, cloth = self.cfg, self.bodies.cloth
        finite = torch.isfinite(x).all(dim=-1).all(dim=-1) & torch.isfinite(v).all(dim=-1).all(dim=-1)
        speed = torch.nan_to_num(v.norm(dim=-1), nan=-1.0).amax(dim=-1)
        length = (x[:, self.edges[:, 1]] - x[:, self.edges[:, 0]]).norm(dim=-1)
        strain = torch.nan_to_num(length / self.rest - 1.0, nan=-1.0).amax(dim=-1)
        blow_up = (speed > cfg.max_speed_m_s) | (strain > cfg.max_edge_strain)
        if len(cloth):
            bodies: list[Bodies] = self.bodies.pose(link_poses, x)
            depth = torch.nan_to_num(self.bodies.depth(x, bodies), nan=0.0)
            if stats is not None:
                torch.maximum(stats["max_depth_after_m"], depth.amax(), out=stats["max_depth_after_m"])
            xc = x[:, cloth]
            outside = torch.nan_to_num(((xc < self.low) | (xc > self.high)).any(dim=-1).float()).amax(dim=-1) > 0
        else:
            depth, outside = torch.zeros_like(speed), torch.zeros_like(finite)
        return torch.stack([~finite, blow_up, depth > cfg.penetration_tol_m, crossing, outside], dim=-1)


class FirstFailures:
    """First failing frame (B, 5) of each FRAME_CHECKS predicate per slot, kept on the device."""

    def __init__(self, batch: int, device: torch.device) -> None:
        self.frames = torch.full((batch, len(FRAME_CHECKS)), NEVER, dtype=torch.long, device=device)

    def record(self, bad: Tensor, frame: Tensor, checked: Tensor) -> None:
        """bad (B, 5) at frame (B,) of each slot; checked (B, 5) bool: the checks this frame counts for (e.g. the
        self-intersection check on every k-th frame, nothing for an idle slot). In place."""
        hit = bad & checked & (self.frames == NEVER)
        self.frames.copy_(torch.where(hit, frame[:, None].expand_as(self.frames), self.frames))

    def reset(self, slots: Tensor) -> None:
        """Slots (bool (B,)) that take a new episode start clean."""
        self.frames.masked_fill_(slots[:, None], NEVER)
