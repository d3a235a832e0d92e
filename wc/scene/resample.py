"""Moving a state between two resolutions of the same object: barycentric maps in rest-position space.

A `SurfaceMap` takes values at a source mesh's vertices (positions, velocities) to target points: each target
point is projected onto the closest triangle of the source rest mesh (exact: every triangle that could be
closer than the best of the nearest few is tested with trimesh's point-triangle query) and takes that triangle's barycentric combination of the values. A map onto the source's own vertices is the
identity, a map onto points of the source surface reproduces them, and the map is linear, so an affine motion
of the source moves the targets by the same affine motion.

`ResolutionMap` does this for every cloth object of a scene built at two resolutions (rigid objects have one
mesh in both and are copied), from the fine scene's concatenated state to the coarse one's and back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from wc.scene.scene import Scene


@dataclass(frozen=True)
class SurfaceMap:
    """target k = sum_j weights[k, j] * source[corners[k, j]]: corners (M, 3) int64, weights (M, 3) float64."""

    corners: np.ndarray
    weights: np.ndarray
    num_source: int

    def apply(self, values: np.ndarray) -> np.ndarray:
        """(..., num_source, D) values at the source vertices -> (..., M, D) at the targets (float64)."""
        values = np.asarray(values, np.float64)
        if values.ndim < 2 or values.shape[-2] != self.num_source:
            raise ValueError(f"expected values (..., {self.num_source}, D) at the source vertices, got {values.shape}")
        return np.einsum("...kjd,kj->...kd", values[..., self.corners, :], self.weights)


def surface_map(source_vertices: np.ndarray, source_faces: np.ndarray, targets: np.ndarray) -> SurfaceMap:
    """The map from a source mesh's vertices (N, 3) with faces (F, 3) to target points (M, 3), all in rest space."""
    source_vertices = np.asarray(source_vertices, np.float64)
    targets = np.asarray(targets, np.float64)
    if source_vertices.ndim != 2 or source_vertices.shape[1] != 3 or targets.ndim != 2 or targets.shape[1] != 3:
        raise ValueError(f"source vertices and targets must be (N, 3) and (M, 3), got {source_vertices.shape} "
                         f"and {targets.shape}")
    faces = np.asarray(source_faces, np.int64)
    triangles = source_vertices[faces]  # (F, 3, 3)
    centroids = triangles.mean(axis=1)
    reach = np.linalg.norm(triangles - centroids[:, None], axis=2).max()  # no triangle point is farther from its centroid
    tree = cKDTree(centroids)
    _, near = tree.query(targets, k=min(8, len(faces)))
    near = near.reshape(len(targets), -1)
    best = np.linalg.norm(_closest(triangles, near, targets) - targets[:, None], axis=2).min(axis=1)
    # a triangle closer than `best` has its centroid within best + reach: test all of those
    candidates = tree.query_ball_point(targets, best + reach + 1e-12)
    target_of = np.repeat(np.arange(len(targets)), [len(c) for c in candidates])
    face_of = np.concatenate([np.sort(np.asarray(c, np.int64)) for c in candidates])
    points = trimesh.triangles.closest_point(triangles[face_of], targets[target_of])
    distance = np.linalg.norm(points - targets[target_of], axis=1)
    order = np.lexsort((face_of, distance, target_of))  # per target: nearest first, ties to the lower face
    first = order[np.r_[0, np.flatnonzero(np.diff(target_of[order])) + 1]]
    triangle, closest = face_of[first], points[first]
    weights = trimesh.triangles.points_to_barycentric(triangles[triangle], closest)
    weights = np.clip(weights, 0.0, None)  # the closest point lies in its triangle: only round-off is negative
    weights /= weights.sum(axis=1, keepdims=True)
    return SurfaceMap(faces[triangle], weights, len(source_vertices))


def _closest(triangles: np.ndarray, faces: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Closest points (M, K, 3) on triangles[faces[m, k]] to targets (M, 3)."""
    m, k = faces.shape
    points = trimesh.triangles.closest_point(triangles[faces.ravel()], np.repeat(targets, k, axis=0))
    return points.reshape(m, k, 3)


class ResolutionMap:
    """State maps between a scene and the same scene with other cloth resolutions (same objects, same order).

    to_coarse: fine concatenated x or v (..., N_fine, 3) -> (..., N_coarse, 3); to_fine: the way back.
    """

    def __init__(self, fine: Scene, coarse: Scene) -> None:
        if list(fine.objects) != list(coarse.objects):
            raise ValueError(f"scenes have different objects: {list(fine.objects)} and {list(coarse.objects)}")
        self.fine_rows, self.coarse_rows = fine.vertex_slices(), coarse.vertex_slices()
        self.num_fine, self.num_coarse = fine.num_vertices, coarse.num_vertices
        self.down: dict[str, SurfaceMap] = {}
        self.up: dict[str, SurfaceMap] = {}
        for name, kind in fine.object_kinds.items():
            f, c = fine.objects[name], coarse.objects[name]
            if kind == "cloth":
                self.down[name] = surface_map(f.vertices, f.faces, c.vertices)
                self.up[name] = surface_map(c.vertices, c.faces, f.vertices)
            elif f.vertices.shape != c.vertices.shape or not np.array_equal(f.vertices, c.vertices):
                raise ValueError(f"rigid object {name!r} differs between the two scenes; only cloth is resampled")

    def _map(self, values: np.ndarray, n_in: int, n_out: int, rows_in: dict[str, slice],
             rows_out: dict[str, slice], maps: dict[str, SurfaceMap]) -> np.ndarray:
        values = np.asarray(values)
        if values.ndim < 2 or values.shape[-2] != n_in:
            raise ValueError(f"expected a state (..., {n_in}, 3), got {values.shape}")
        out = np.empty((*values.shape[:-2], n_out, values.shape[-1]), np.float64)
        for name, rows in rows_in.items():
            part = values[..., rows, :]
            out[..., rows_out[name], :] = maps[name].apply(part) if name in maps else part
        return out

    def to_coarse(self, values: np.ndarray) -> np.ndarray:
        return self._map(values, self.num_fine, self.num_coarse, self.fine_rows, self.coarse_rows, self.down)

    def to_fine(self, values: np.ndarray) -> np.ndarray:
        return self._map(values, self.num_coarse, self.num_fine, self.coarse_rows, self.fine_rows, self.up)
