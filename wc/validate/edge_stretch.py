"""How far a cloth's rest edges are stretched along a trajectory: per-frame edge strains (length / rest - 1, the
quantity the blow-up check bounds by `validate.max_edge_strain`) and their distribution over chosen frames.

The edges are the mesh's unique triangle edges (`unique_edges`, as the blow-up and self-intersection checks take
them); a subset of them (e.g. the bag's handle straps, `group_edges`) can be summarised on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.validate.self_intersection import unique_edges

STRETCH_LIMIT = 0.05  # the summary's share counts strains above this by default


def edge_strain(x: np.ndarray, edges: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """(..., E) strain length / rest - 1 of `edges` (E, 2) in positions x (..., N, 3) [m]; non-finite x gives NaN."""
    length = np.linalg.norm(x[..., edges[:, 0], :] - x[..., edges[:, 1], :], axis=-1)
    return length / np.maximum(rest, 1e-12) - 1.0


@dataclass(frozen=True)
class RestEdges:
    """A mesh's unique edges (E, 2) and their rest lengths (E,) [m]."""

    edges: np.ndarray
    length: np.ndarray

    @classmethod
    def of_mesh(cls, vertices: np.ndarray, faces: np.ndarray) -> RestEdges:
        """The edges of triangles `faces` (F, 3) over rest `vertices` (N, 3) [m]."""
        vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
            raise ValueError(f"edge stretch: rest vertices must be finite (N, 3), got shape {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"edge stretch: faces must be (F >= 1, 3), got shape {faces.shape}")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"edge stretch: face indices must lie in [0, {len(vertices)}), got "
                             f"[{faces.min()}, {faces.max()}]")
        edges = unique_edges(faces)
        length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=-1)
        if not (length > 0).all():
            raise ValueError(f"edge stretch: {int((length <= 0).sum())} rest edges have zero length")
        return cls(edges, length)

    def strains(self, x: np.ndarray) -> np.ndarray:
        """(T, E) strain length / rest - 1 of every edge in each frame of x (T, N, 3) [m]."""
        x = np.asarray(x)
        if x.ndim != 3 or x.shape[2] != 3:
            raise ValueError(f"edge stretch: x must be (T, N, 3), got shape {x.shape}")
        if x.shape[1] <= self.edges.max():
            raise ValueError(f"edge stretch: x has {x.shape[1]} vertices, the edges need {self.edges.max() + 1}")
        if not np.isfinite(x).all():
            bad = np.flatnonzero(~np.isfinite(x).all(axis=(1, 2)))
            raise ValueError(f"edge stretch: x is not finite in {len(bad)} frames (first {bad[0]})")
        return edge_strain(x, self.edges, self.length)


def group_edges(edges: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(E,) bool: the edges whose two ends are both among `vertices` (indices, e.g. a mesh group)."""
    edges = np.asarray(edges)
    if edges.ndim != 2 or edges.shape[1] != 2:
        raise ValueError(f"edge stretch: edges must be (E, 2), got shape {edges.shape}")
    return np.isin(edges, np.asarray(vertices)).all(axis=1)


def stretch_summary(strain: np.ndarray, limit: float = STRETCH_LIMIT) -> dict[str, float | int] | None:
    """Distribution of edge strains (any shape, e.g. (T, E) over chosen frames, pooled): p50, p90, p99, max, and
    `share_above_limit`, the share of (frame, edge) samples strained beyond `limit`; `samples` counts them.
    None without samples."""
    strain = np.asarray(strain, np.float64).ravel()
    if not np.isfinite(strain).all():
        raise ValueError(f"edge stretch: {int((~np.isfinite(strain)).sum())} strains are not finite")
    if not len(strain):
        return None
    p50, p90, p99 = np.percentile(strain, [50, 90, 99])
    return {"p50": float(p50), "p90": float(p90), "p99": float(p99), "max": float(strain.max()),
            "limit": float(limit), "share_above_limit": float((strain > limit).mean()), "samples": len(strain)}
