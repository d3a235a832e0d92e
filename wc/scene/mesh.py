"""Object surface meshes: the `ObjectMesh` record and the helpers every object builder shares.

An `ObjectMesh` is what the trajectory store keeps under objects/<name>/ (rest_positions = vertices,
faces, rest_uv, vertex_area, tag), plus named vertex groups and per-vertex attributes that task
programs use (e.g. where a handle is) but the store does not need.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

DEFAULT_MIN_FACE_AREA_M2 = 1e-12  # below this a triangle counts as degenerate


@dataclass
class ObjectMesh:
    """A triangle surface mesh in its rest shape.

    vertices (N, 3) float32 m; faces (F, 3) int32, counter-clockwise seen from outside;
    rest_uv (N, 2) float32 m, coordinates in the object's own 2D pattern space;
    vertex_area (N,) float32 m^2, lumped (a third of each incident triangle);
    groups: name -> vertex indices (int64); attributes: name -> per-vertex array (N, ...).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    rest_uv: np.ndarray
    vertex_area: np.ndarray
    tag: int
    groups: dict[str, np.ndarray] = field(default_factory=dict)
    attributes: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        self.rest_uv = np.ascontiguousarray(self.rest_uv, dtype=np.float32)
        self.vertex_area = np.ascontiguousarray(self.vertex_area, dtype=np.float32)
        self.groups = {k: np.asarray(v, dtype=np.int64) for k, v in self.groups.items()}

    @property
    def num_vertices(self) -> int:
        return len(self.vertices)

    def to_trimesh(self) -> trimesh.Trimesh:
        """The mesh as an unprocessed trimesh (vertex order and faces kept as they are)."""
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def lumped_vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Lumped area per vertex (N,) float64 m^2: each triangle gives a third of its area to each corner."""
    tri = np.asarray(vertices, dtype=np.float64)[faces]
    face_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.bincount(np.asarray(faces).ravel(), weights=np.repeat(face_area / 3.0, 3), minlength=len(vertices))


def grid_faces(index_grid: np.ndarray) -> np.ndarray:
    """Triangulate a structured grid of vertex indices (nu+1, nv+1) -> faces (2*nu*nv, 3) int64.

    Triangles are counter-clockwise in (axis 0, axis 1), so the normal is d/du x d/dv of the
    surface the grid samples. Diagonals alternate in a checkerboard so that the triangulation has
    no preferred shear direction. Grids stitch to each other by sharing entries of `index_grid`.
    """
    g = np.asarray(index_grid)
    a, b, c, d = g[:-1, :-1], g[1:, :-1], g[1:, 1:], g[:-1, 1:]
    flip = (np.add.outer(np.arange(a.shape[0]), np.arange(a.shape[1])) % 2).astype(bool)[..., None]
    first = np.where(flip, np.stack([a, b, d], -1), np.stack([a, b, c], -1))
    second = np.where(flip, np.stack([b, c, d], -1), np.stack([a, c, d], -1))
    return np.concatenate([first.reshape(-1, 3), second.reshape(-1, 3)])


class VertexPool:
    """Collects vertices and their uv piece by piece; `add` returns the new vertices' indices."""

    def __init__(self) -> None:
        self._xyz: list[np.ndarray] = []
        self._uv: list[np.ndarray] = []
        self.count = 0

    def add(self, xyz: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Append points xyz (..., 3) m with uv (..., 2) m; returns their indices, shape (...)."""
        xyz, uv = np.asarray(xyz, dtype=np.float64), np.asarray(uv, dtype=np.float64)
        ids = self.count + np.arange(xyz[..., 0].size).reshape(xyz.shape[:-1])
        self._xyz.append(xyz.reshape(-1, 3))
        self._uv.append(uv.reshape(-1, 2))
        self.count += xyz[..., 0].size
        return ids

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """All vertices (N, 3) and uv (N, 2), float64, in index order."""
        return np.concatenate(self._xyz), np.concatenate(self._uv)


def check_mesh(mesh: ObjectMesh, *, closed: bool = False,
               min_face_area_m2: float = DEFAULT_MIN_FACE_AREA_M2) -> None:
    """Raise ValueError unless `mesh` is a valid simulation mesh.

    Checks: array shapes, finite values, face indices in range, every vertex referenced, no
    degenerate (area < min_face_area_m2) or duplicate faces, every edge shared by at most two
    faces, consistent winding, a single edge-connected piece, valid groups and attributes; with
    `closed`, also watertight with positive volume (outward normals).
    """
    v, f, n = mesh.vertices, mesh.faces, len(mesh.vertices)
    name = mesh.name
    if v.ndim != 2 or v.shape[1] != 3 or n == 0:
        raise ValueError(f"{name}: vertices must be (N, 3) with N > 0, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"{name}: faces must be (F, 3) with F > 0, got {f.shape}")
    if mesh.rest_uv.shape != (n, 2) or mesh.vertex_area.shape != (n,):
        raise ValueError(f"{name}: rest_uv {mesh.rest_uv.shape} / vertex_area {mesh.vertex_area.shape} "
                         f"do not match {n} vertices")
    for key, arr in (("vertices", v), ("rest_uv", mesh.rest_uv), ("vertex_area", mesh.vertex_area)):
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}: {key} has non-finite values")
    if f.min() < 0 or f.max() >= n:
        raise ValueError(f"{name}: face indices out of range [0, {n})")
    unreferenced = np.setdiff1d(np.arange(n), f)
    if len(unreferenced):
        raise ValueError(f"{name}: {len(unreferenced)} unreferenced vertices, e.g. {unreferenced[:5]}")

    tm = mesh.to_trimesh()
    degenerate = np.flatnonzero(tm.area_faces < min_face_area_m2)
    if len(degenerate):
        raise ValueError(f"{name}: {len(degenerate)} degenerate faces (area < {min_face_area_m2} m^2), "
                         f"e.g. {degenerate[:5]}")
    if len(np.unique(np.sort(f, axis=1), axis=0)) != len(f):
        raise ValueError(f"{name}: duplicate faces")
    _, edge_use = np.unique(tm.edges_sorted, axis=0, return_counts=True)
    if edge_use.max() > 2:
        raise ValueError(f"{name}: {int((edge_use > 2).sum())} non-manifold edges (shared by > 2 faces)")
    if not tm.is_winding_consistent:
        raise ValueError(f"{name}: inconsistent face winding")
    labels = trimesh.graph.connected_component_labels(tm.face_adjacency, node_count=len(f))
    if labels.max() != 0:
        raise ValueError(f"{name}: {labels.max() + 1} connected components, expected 1")
    if closed and not (tm.is_watertight and tm.volume > 0):
        raise ValueError(f"{name}: not a closed surface with outward normals "
                         f"(watertight={tm.is_watertight}, volume={tm.volume:.3g})")

    for key, ids in mesh.groups.items():
        if ids.ndim != 1 or (len(ids) and (ids.min() < 0 or ids.max() >= n)):
            raise ValueError(f"{name}: group {key!r} has indices out of range [0, {n})")
    for key, arr in mesh.attributes.items():
        if len(arr) != n:
            raise ValueError(f"{name}: attribute {key!r} has length {len(arr)}, expected {n}")
