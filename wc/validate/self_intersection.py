"""Triangle-triangle intersection of a surface mesh: two non-coplanar triangles intersect iff an edge of one crosses
the other, so every mesh edge is tested against the triangles that share no vertex with it (those that do touch it by
construction). The test runs on many states at once through one grouped BVH (wc.validate.cloth_bvh): the frames of
an episode here, the episodes of a batch in the expansion's rollback guard and checks, the same kernel for both.
"""

from __future__ import annotations

import numpy as np

from wc.validate.cloth_bvh import crossing_faces

FRAMES_PER_CALL = 64  # states per BVH in `first_crossing_frame` (bounds memory)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) int32 vertex pairs (sorted) of a triangle mesh's edges, each once."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0).astype(np.int32)


def crossing_edges(points: np.ndarray, faces: np.ndarray, edges: np.ndarray, device: str = "cpu") -> np.ndarray:
    """Per edge (E,) the index of a non-adjacent face it crosses, or -1. points (N, 3) m, faces (F, 3)."""
    return crossing_faces(np.asarray(points)[None], faces, edges, device)[0]


def first_crossing_frame(points: np.ndarray, faces: np.ndarray, edges: np.ndarray, device: str = "cpu"
                         ) -> int | None:
    """The first of the states points (T, N, 3) [m] in which an edge crosses a non-adjacent face, or None."""
    for t0 in range(0, len(points), FRAMES_PER_CALL):
        crossing = (crossing_faces(points[t0:t0 + FRAMES_PER_CALL], faces, edges, device) >= 0).any(axis=1)
        if crossing.any():
            return t0 + int(np.flatnonzero(crossing)[0])
    return None
