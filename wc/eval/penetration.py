"""Area-weighted cloth penetration from exact signed distances (paper Table 1, "penetration rate").

A cloth vertex carries its lumped area (store `vertex_area`). Its signed distance (negative inside) is the
minimum over the collision geometry: the table box and the robot's link and finger-pad boxes (analytic,
wc.validate.predicates.table_and_robot_distance) and every rigid object, predicted (pose fitted to its
rows of x) or held (pose from link_poses), as a closed triangle mesh queried with warp
(wp.mesh_query_point: closest point, inside/outside by ray votes).

    penetration rate (%)          = area deeper than `depth_m` / cloth area,        summed over frames
    contact penetration rate (%)  = area deeper than `depth_m` / area within `band_m` (signed distance
                                    below band_m, penetrating vertices included),  summed over frames
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import wc.warp_settings  # noqa: F401  (first: kernels take warp's settings when defined)
import warp as wp

from wc.scene.scene import Scene
from wc.validate.predicates import Episode, cloth_rows, rigid_poses, table_and_robot_distance


@wp.kernel
def _mesh_signed_distance(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float,
                          out: wp.array(dtype=float)):
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point(mesh, p, max_dist)
    if q.result:
        out[i] = q.sign * wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))


class _MeshCache:
    """warp meshes of rest shapes, built once per distinct (vertices, faces)."""

    def __init__(self) -> None:
        self._meshes: dict[tuple, tuple[wp.Mesh, float]] = {}

    def get(self, vertices: np.ndarray, faces: np.ndarray) -> tuple[wp.Mesh, float]:
        """(mesh, radius [m] of the ball about the rest origin that holds it)."""
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.int32)
        key = (v.shape, f.shape, hash(v.tobytes()), hash(f.tobytes()))
        if key not in self._meshes:
            with wp.ScopedDevice("cpu"):
                mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3), indices=wp.array(f.ravel(), dtype=wp.int32))
            self._meshes[key] = (mesh, float(np.linalg.norm(v, axis=1).max(initial=0.0)))
        return self._meshes[key]


_MESHES = _MeshCache()


def mesh_signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, pos: np.ndarray,
                         rot: np.ndarray, reach_m: float) -> np.ndarray:
    """(T, N) signed distance [m] (negative inside) of points (T, N, 3) to a closed, outward-wound triangle mesh
    (rest vertices (V, 3), faces (F, 3)) posed per frame by pos (T, 3), rot (T, 3, 3) (rest -> world).

    Exact wherever the distance is below reach_m or the point is inside; +inf for points farther than the
    mesh's diameter + reach_m from every face (far outside, never needed).
    """
    mesh, radius = _MESHES.get(vertices, faces)
    p = np.asarray(points, np.float64)
    local = np.einsum("tni,tij->tnj", p - np.asarray(pos, np.float64)[:, None], np.asarray(rot, np.float64))
    flat = np.ascontiguousarray(local.reshape(-1, 3), np.float32)
    with wp.ScopedDevice("cpu"):
        out = wp.full(len(flat), np.inf, dtype=float)
        if len(flat):
            wp.launch(_mesh_signed_distance, dim=len(flat),
                      inputs=[mesh.id, wp.array(flat, dtype=wp.vec3), 2.0 * radius + reach_m, out])
        return out.numpy().astype(np.float64).reshape(p.shape[:2])


def cloth_signed_distance(scene: Scene, x: np.ndarray, link_poses: np.ndarray, reach_m: float) -> np.ndarray:
    """(T, N_cloth) signed distance [m] of the cloth vertices to the nearest collision geometry; NaN rows for
    frames where x is not finite (a diverged rollout).

    x (T, N, 3): every predicted object of `scene` (rows in scene.vertex_slices order);
    link_poses (T, L, 7) in scene.link_names order. Exact below reach_m (see table_and_robot_distance).
    """
    x = np.asarray(x, np.float64)
    rows = cloth_rows(scene)
    out = np.full((len(x), len(rows)), np.nan)
    ok = np.isfinite(x).all(axis=(1, 2))
    if not ok.any() or len(rows) == 0:
        return out
    xs, poses = x[ok], np.asarray(link_poses)[ok]
    d = table_and_robot_distance(scene, xs[:, rows], poses, reach_m)
    ep = Episode(xs, xs, np.zeros((len(xs), 14)), poses, 1.0)  # rigid_poses reads only x and link_poses
    for _, mesh, pos, rot in rigid_poses(scene, ep):
        d = np.minimum(d, mesh_signed_distance(xs[:, rows], mesh.vertices, mesh.faces, pos, rot, reach_m))
    out[ok] = d
    return out


def penetrating_area_pct(signed_distance: np.ndarray, area: np.ndarray, depth_m: float) -> np.ndarray:
    """(T,) % of cloth area deeper than depth_m in each frame (NaN for NaN rows); signed_distance (T, N) m,
    area (N,) m^2."""
    d = np.asarray(signed_distance, np.float64)
    pct = 100.0 * ((d < -depth_m) * area).sum(axis=1) / max(float(np.sum(area)), 1e-30)
    return np.where(np.isnan(d).any(axis=1), np.nan, pct)


@dataclass
class PenetrationTally:
    """Cloth areas summed over frames [m^2]: all, penetrating deeper than depth_m, within band_m (contact)."""

    depth_m: float
    band_m: float
    area_m2: float = 0.0
    penetrating_m2: float = 0.0
    contact_m2: float = 0.0
    frames: int = 0

    def add(self, signed_distance: np.ndarray, area: np.ndarray) -> None:
        """Count frames of signed distances (T, N) m of cloth vertices with areas (N,) m^2; NaN rows are skipped."""
        d = np.asarray(signed_distance, np.float64)
        a = np.asarray(area, np.float64)
        if d.ndim != 2 or d.shape[1] != a.shape[0]:
            raise ValueError(f"signed_distance must be (T, {a.shape[0]}), got {d.shape}")
        d = d[~np.isnan(d).any(axis=1)]  # frames of a diverged rollout carry no geometry
        inside = d < -self.depth_m  # a subset of the contact band: -depth_m <= 0 < band_m
        contact = d < self.band_m
        self.area_m2 += float(a.sum()) * len(d)
        self.penetrating_m2 += float((inside * a).sum())
        self.contact_m2 += float((contact * a).sum())
        self.frames += len(d)

    @property
    def rate_pct(self) -> float:
        """% of cloth area (over all frames) penetrating deeper than depth_m; NaN with no frames."""
        return 100.0 * self.penetrating_m2 / self.area_m2 if self.area_m2 > 0 else float("nan")

    @property
    def contact_rate_pct(self) -> float:
        """% of the contact area (within band_m, over all frames) penetrating deeper than depth_m; 0 without contact."""
        if self.frames == 0:
            return float("nan")
        return 100.0 * self.penetrating_m2 / self.contact_m2 if self.contact_m2 > 0 else 0.0
