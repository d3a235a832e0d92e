"""Triangle-triangle intersection of a surface mesh via warp ray casts along its edges.

Two non-coplanar triangles intersect iff an edge of one crosses the other, so casting every mesh
edge as a ray (max_t = edge length) against the mesh's BVH finds every crossing. Triangles that
share a vertex with the edge touch it by construction and are skipped (the ray restarts just past them).
"""

from __future__ import annotations

import numpy as np
import warp as wp

MAX_SKIPS = 64  # adjacent-triangle hits skipped per edge; an edge that needs more is reported unchecked (an error)
UNCHECKED = -2  # hit_face of an edge whose ray ran out of skips before its far end
SKIP_EPS = 1.0e-5  # restart offset past an adjacent hit, as a fraction of the edge length


@wp.kernel
def _edge_crossings(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), edges: wp.array(dtype=wp.vec2i),
                    faces: wp.array(dtype=wp.int32), max_skips: int, hit_face: wp.array(dtype=wp.int32)):
    e = wp.tid()
    a = edges[e][0]
    b = edges[e][1]
    start = points[a]
    d = points[b] - start
    length = wp.length(d)
    if length <= 0.0:
        return
    dir = d / length
    t0 = float(0.0)
    skips = int(0)
    while skips < max_skips and t0 < length:
        q = wp.mesh_query_ray(mesh, start + dir * t0, dir, length - t0)
        if not q.result:
            return
        i0 = faces[3 * q.face]
        i1 = faces[3 * q.face + 1]
        i2 = faces[3 * q.face + 2]
        if i0 == a or i1 == a or i2 == a or i0 == b or i1 == b or i2 == b:
            t0 = t0 + q.t + SKIP_EPS * length
            skips += 1
        else:
            hit_face[e] = q.face
            return
    if t0 < length:
        hit_face[e] = UNCHECKED


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) int32 vertex pairs (sorted) of a triangle mesh's edges, each once."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0).astype(np.int32)


def crossing_edges(points: np.ndarray, faces: np.ndarray, edges: np.ndarray, device: str = "cpu",
                   max_skips: int = MAX_SKIPS) -> np.ndarray:
    """Per edge (E,) the index of a non-adjacent face it crosses, or -1. points (N, 3) m, faces (F, 3).
    RuntimeError if an edge could not be checked to its end (more than MAX_SKIPS adjacent hits)."""
    with wp.ScopedDevice(device):
        pts = wp.array(np.ascontiguousarray(points, np.float32), dtype=wp.vec3)
        idx = wp.array(np.ascontiguousarray(faces, np.int32).ravel())
        mesh = wp.Mesh(points=pts, indices=idx)
        hit = wp.full(len(edges), -1, dtype=wp.int32)
        wp.launch(_edge_crossings, dim=len(edges),
                  inputs=[mesh.id, pts, wp.array(np.ascontiguousarray(edges, np.int32), dtype=wp.vec2i), idx, int(max_skips), hit])
        hits = hit.numpy()
    unchecked = np.flatnonzero(hits == UNCHECKED)
    if len(unchecked):  # never pass an edge that was not checked to its end
        raise RuntimeError(f"self-intersection check: {len(unchecked)} edges (first {edges[unchecked[0]].tolist()}) "
                           f"hit more than {max_skips} adjacent triangles; the frame was not checked")
    return hits
