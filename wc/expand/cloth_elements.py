"""A scene's cloth as element tables (vertices, edges, triangles in the state's rows), and the static-shape helpers
of the fast expansion path: pair compaction without a host sync, per-episode gathers. Nothing is bag-specific: every
cloth object of a scene."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
import torch
from torch import Tensor

from wc.validate.self_intersection import unique_edges


@dataclass(frozen=True)
class ClothElements:
    """Every cloth mesh of a scene as element tables in the scene's vertex rows."""

    vertices: Tensor  # (V,) rows of the cloth vertices
    vertex_mesh: Tensor  # (V,) cloth mesh index of each
    faces: Tensor  # (F, 3) rows
    face_mesh: Tensor  # (F,)
    edges: Tensor  # (E, 2) rows, each once
    edge_mesh: Tensor  # (E,)
    meshes: int
    rows: int  # rows of the scene's state x (every predicted object)

    @classmethod
    def of_scene(cls, scene) -> ClothElements:  # noqa: ANN001 - wc.scene.scene.Scene
        slices = scene.vertex_slices()
        parts = [(slices[n].start, np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64))
                 for n, m in scene.objects.items() if scene.object_kinds[n] == "cloth"]
        rows = sum(len(m.vertices) for m in scene.objects.values())
        vertices, vmesh, faces, fmesh, edges, emesh = [], [], [], [], [], []
        for k, (start, rest, f) in enumerate(parts):
            e = unique_edges(f).astype(np.int64)
            vertices.append(start + np.arange(len(rest)))
            faces.append(start + f)
            edges.append(start + e)
            vmesh.append(np.full(len(rest), k))
            fmesh.append(np.full(len(f), k))
            emesh.append(np.full(len(e), k))

        def cat(a: list[np.ndarray], shape: tuple[int, ...]) -> Tensor:
            return torch.as_tensor(np.concatenate(a) if a else np.zeros(shape, np.int64), dtype=torch.long)

        return cls(cat(vertices, (0,)), cat(vmesh, (0,)), cat(faces, (0, 3)), cat(fmesh, (0,)), cat(edges, (0, 2)),
                   cat(emesh, (0,)), len(parts), rows)

    def to(self, device: torch.device | str) -> ClothElements:
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in fields(self)
                                if isinstance(getattr(self, f.name), Tensor)})


def compact(valid: Tensor, capacity: int | None) -> tuple[Tensor, Tensor, Tensor]:
    """The True entries of valid (any shape) as indices (P,) into valid.reshape(-1), their mask (P,) and the count
    that did not fit (()). capacity None: exactly the True entries (reads the count: for the CPU, where nothing is
    captured); else P = capacity slots filled in order by a prefix sum, no host sync (unused slots masked)."""
    flat = valid.reshape(-1)
    if capacity is None:
        idx = flat.nonzero().squeeze(1)
        return idx, torch.ones_like(idx, dtype=torch.bool), flat.new_zeros((), dtype=torch.long)
    pos = flat.long().cumsum(0) - 1
    slot = torch.where(flat & (pos < capacity), pos, capacity)  # slot `capacity` collects what does not fit
    idx = torch.zeros(capacity + 1, dtype=torch.long, device=flat.device)
    idx.scatter_(0, slot, torch.arange(flat.numel(), device=flat.device))
    count = flat.sum()
    return idx[:capacity], torch.arange(capacity, device=flat.device) < count, (count - capacity).clamp_min(0)


def spread_unused(index: Tensor, valid: Tensor, size: int) -> Tensor:
    """Scatter targets (M,) of a padded pair list with its unused entries sent to distinct rows (k mod size). Unused
    entries add zeros wherever they point, but a capacity's worth of them on one row (compact's padding all points at
    entry 0) serialises the device's atomic adds on that row."""
    return torch.where(valid, index, torch.arange(len(index), device=index.device) % size)


def host_checks(t: Tensor) -> bool:
    """Whether loops over tensors on t's device may read values back to stop early (the CPU: nothing is captured in a
    graph and a read costs nothing) or must run their fixed passes (CUDA)."""
    return t.device.type == "cpu"
