"""Named episode checks: each returns the first failing frame index, or None when the episode passes.

Every predicate is a pure function `(scene, episode, cfg) -> int | None`; `first_failure` runs them
in the fixed order of PREDICATES (non-finite first, so later checks may assume finite arrays) and
reports the first predicate that fails. Cloth checks (penetration, self-intersection, adhesion,
workspace, view) look at the cloth objects' vertices; non_finite and blow_up at all predicted vertices.
The scene may hold any subset of objects (and held objects): without cloth the cloth checks pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from wc.devices import resolve_warp_device
from wc.scene.cameras import camera_pose, intrinsics
from wc.scene.mesh import ObjectMesh
from wc.scene.piper import PAD_CENTRE_IN_FINGER_M, PAD_HALF_EXTENTS_M
from wc.scene.scene import Scene
from wc.rotations import quat_conjugate, quat_matrices, quat_multiply, quat_rotate
from wc.validate.config import ValidateConfig
from wc.validate.edge_stretch import edge_strain
from wc.validate.self_intersection import first_crossing_frame, unique_edges

OPENING_COLUMNS = {"left": 6, "right": 13}  # action = [q_L (6), d_L, q_R (6), d_R]
CHUNK_ELEMENTS = 4_000_000  # frames x vertices x boxes (or planes) evaluated at once by the distances
CONVEX_TOL = 1e-6  # relative to the object's size: coplanar faces merge, convexity is checked, at this tolerance


@dataclass(frozen=True)
class Episode:
    """One episode's arrays: x, v (T, N, 3) m, m/s; action (T, 14); link_poses (T, L, 7); frame dt s."""

    x: np.ndarray
    v: np.ndarray
    action: np.ndarray
    link_poses: np.ndarray
    frame_dt_s: float


def _first(bad: np.ndarray) -> int | None:
    """First True frame of a (T,) mask."""
    hits = np.flatnonzero(bad)
    return int(hits[0]) if len(hits) else None


def cloth_rows(scene: Scene) -> np.ndarray:
    """Rows of x that belong to cloth objects (the bag)."""
    slices = scene.vertex_slices()
    rows = [np.arange(slices[n].start, slices[n].stop) for n, kind in scene.object_kinds.items() if kind == "cloth"]
    return np.concatenate(rows) if rows else np.zeros(0, np.int64)


def box_signed_distance(points: np.ndarray, centre: np.ndarray, quat: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Exact signed distance [m] (negative inside) of points (..., 3) to oriented boxes broadcasting with them:
    centre (..., 3), quat xyzw (..., 4), half extents (..., 3)."""
    q = np.abs(quat_rotate(quat_conjugate(quat), points - centre)) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    return outside + np.minimum(q.max(axis=-1), 0.0)


def robot_box_shapes(scene: Scene, links: tuple[str, ...] | None = None) -> list[tuple[int, object]]:
    """(index in scene.link_names, box shape) of the robot's box link shapes, in robot_boxes' order.

    links: prefixed body names to include (default: every arm body); capsules are not handled.
    """
    shapes: dict[str, list] = {}
    for s in scene.link_shapes:
        if s.kind == "box":
            shapes.setdefault(s.link, []).append(s)
    out = []
    for k, name in enumerate(scene.link_names):
        side, _, link = name.partition("_")
        if side in OPENING_COLUMNS and (links is None or name in links):
            out += [(k, s) for s in shapes.get(link, [])]
    return out


def robot_boxes(scene: Scene, link_poses: np.ndarray, links: tuple[str, ...] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World boxes of the robot's link shapes (robot_box_shapes): centres (T, B, 3), quats (T, B, 4), half extents
    (B, 3)."""
    boxes = robot_box_shapes(scene, links)
    cols = [k for k, _ in boxes]
    pos = np.asarray([s.local_pos for _, s in boxes], np.float64).reshape(-1, 3)
    quat = np.asarray([s.local_quat_xyzw for _, s in boxes], np.float64).reshape(-1, 4)
    body = np.asarray(link_poses, np.float64)[:, cols]
    centre = body[..., :3] + quat_rotate(body[..., 3:], pos[None])
    q = quat_multiply(body[..., 3:], np.broadcast_to(quat, body[..., 3:].shape))
    return centre, q, np.asarray([s.size for _, s in boxes], np.float64).reshape(-1, 3)


def _min_box_distance(x: np.ndarray, centre: np.ndarray, quat: np.ndarray, half: np.ndarray,
                      reach_m: float = 0.0) -> np.ndarray:
    """(T, N) signed distance of points x (T, N, 3) to the nearest of the boxes (T, B, ...); +inf where no box
    is near. Broad phase: only (frame, box) pairs whose bounding sphere, grown by reach_m, reaches the points'
    bounding box, so every distance below reach_m is exact."""
    T, N = x.shape[:2]
    out = np.full((T, N), np.inf)
    if len(half) == 0 or N == 0:
        return out
    lo, hi = x.min(axis=1), x.max(axis=1)  # (T, 3)
    gap = np.linalg.norm(np.maximum(np.maximum(lo[:, None] - centre, centre - hi[:, None]), 0.0), axis=-1)
    pairs = np.argwhere(gap <= np.linalg.norm(half, axis=-1)[None] + reach_m)  # (P, 2) frame, box
    step = max(1, CHUNK_ELEMENTS // N)
    for p0 in range(0, len(pairs), step):
        t, b = pairs[p0:p0 + step].T
        d = box_signed_distance(x[t], centre[t, b][:, None], quat[t, b][:, None], half[b][:, None])
        np.minimum.at(out, t, d)
    return out


def non_finite(scene: Scene, ep: Episode, cfg: ValidateConfig) -> int | None:
    """First frame with a NaN or Inf in x or v."""
    bad = ~(np.isfinite(ep.x).all(axis=(1, 2)) & np.isfinite(ep.v).all(axis=(1, 2)))
    return _first(bad)


def speed_and_strain(scene: Scene, ep: Episode) -> tuple[np.ndarray, np.ndarray]:
    """Per frame (T,): the fastest vertex speed [m/s] and the largest rest-edge strain (length / rest - 1)."""
    speed = _nan_max(np.linalg.norm(ep.v, axis=-1))
    strain = np.full(len(ep.x), -np.inf)
    slices = scene.vertex_slices()
    for name, mesh in scene.objects.items():
        edges = unique_edges(mesh.faces)
        rest = np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], axis=-1)
        strain = np.maximum(strain, _nan_max(edge_strain(ep.x[:, slices[name]], edges, rest)))
    return speed, strain


def _nan_max(a: np.ndarray) -> np.ndarray:
    """Per frame max of a (T, n) ignoring NaN (non_finite judges those); -inf for a frame without a value."""
    return np.where(np.isnan(a), -np.inf, a).max(axis=1, initial=-np.inf)


def blow_up(scene: Scene, ep: Episode, cfg: ValidateConfig) -> int | None:
    """First frame with a vertex faster than max_speed_m_s or a rest edge strained beyond max_edge_strain."""
    speed, strain = speed_and_strain(scene, ep)
    return _first((speed > cfg.max_speed_m_s) | (strain > cfg.max_edge_strain))


def convex_planes(vertices: np.ndarray, faces: np.ndarray, name: str = "object"
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """Distinct face planes of a closed convex mesh in its rest frame: outward unit normals (P, 3),
    offsets (P,) [m] with n . p = offset on the plane, and the radius [m] of the ball about the rest
    origin that holds the mesh.

    Convexity is assumed by the penetration depth below (and checked here: ValueError if a vertex lies
    outside a face plane); faces must be counter-clockwise seen from outside. Coplanar faces (a cube's
    grid) share one plane.
    """
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces, np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1)
    keep = length > 1e-12 * max(1.0, float(length.max(initial=0.0)))  # drop degenerate triangles
    n = n[keep] / length[keep, None]
    offset = np.einsum("fi,fi->f", n, tri[keep, 0])
    radius = float(np.linalg.norm(v, axis=1).max(initial=0.0))
    tol = CONVEX_TOL * max(radius, 1e-9)
    _, first = np.unique(np.round(np.c_[n, offset / max(radius, 1e-9)] / CONVEX_TOL), axis=0, return_index=True)
    n, offset = n[np.sort(first)], offset[np.sort(first)]
    if len(n) < 4:
        raise ValueError(f"{name}: rigid-object penetration needs a closed convex mesh, got {len(n)} face planes")
    outside = v @ n.T - offset  # (N, P): <= 0 for every vertex of a convex mesh
    if outside.max() > tol:
        worst = int(np.argmax(outside.max(axis=1)))
        raise ValueError(f"{name}: rigid-object penetration assumes a closed convex mesh with outward faces; "
                         f"vertex {worst} lies {outside.max() * 1e3:.3f} mm outside a face plane")
    return n, offset, radius


def convex_depth(x: np.ndarray, pos: np.ndarray, rot: np.ndarray,
                 planes: tuple[np.ndarray, np.ndarray, float]) -> np.ndarray:
    """(T,) deepest penetration [m] of points x (T, N, 3) into a convex body at world pose pos (T, 3),
    rot (T, 3, 3) (rest frame -> world), -inf where no point is inside.

    The depth of p inside a convex polytope is its distance to the nearest face plane,
    -max_f (n_f . p_local - offset_f); only points within the body's bounding ball are evaluated.
    """
    normals, offsets, radius = planes
    T, N = x.shape[:2]
    out = np.full(T, -np.inf)
    if N == 0 or len(normals) == 0:
        return out
    frames = max(1, CHUNK_ELEMENTS // N)
    rows = max(1, CHUNK_ELEMENTS // len(normals))
    for t0 in range(0, T, frames):
        d = np.asarray(x[t0:t0 + frames], np.float64) - pos[t0:t0 + frames, None]  # (t, N, 3)
        t, i = np.nonzero(np.einsum("tni,tni->tn", d, d) <= radius * radius)
        if not len(t):
            continue
        local = np.einsum("pi,pij->pj", d[t, i], rot[t0 + t])  # R^T d, rows
        for p0 in range(0, len(t), rows):
            depth = -(local[p0:p0 + rows] @ normals.T - offsets).max(axis=1)
            np.maximum.at(out, t0 + t[p0:p0 + rows], depth)
    return out


def rigid_frames(rest: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best-fit rigid poses (Kabsch, per frame) mapping rest vertices (N, 3) onto x (T, N, 3):
    positions (T, 3) of the rest origin and rotations (T, 3, 3), x ~ rest @ R^T + pos."""
    rest = np.asarray(rest, np.float64)
    x = np.asarray(x, np.float64)
    rc, xc = rest.mean(axis=0), x.mean(axis=1)
    h = np.einsum("ni,tnj->tij", rest - rc, x - xc[:, None])
    u, _, vt = np.linalg.svd(h)
    v, ut = vt.transpose(0, 2, 1), u.transpose(0, 2, 1)
    flip = np.where(np.linalg.det(v @ ut) < 0, -1.0, 1.0)  # no reflections
    v[:, :, 2] *= flip[:, None]
    rot = v @ ut
    return xc - rot @ rc, rot


def rigid_poses(scene: Scene, ep: Episode) -> list[tuple[str, ObjectMesh, np.ndarray, np.ndarray]]:
    """(name, rest mesh, pos (T, 3), rot (T, 3, 3)) of every rigid body the cloth may touch: predicted
    rigid objects (fitted to their rows of x) and held objects (their link_poses column `held_<object>`).
    A held object that is also predicted (a hand-off) is skipped: its rows of x follow the held pose
    while it is held, so the fitted pose covers it."""
    out = []
    slices = scene.vertex_slices()
    for name, mesh in scene.objects.items():
        if scene.object_kinds[name] == "rigid":
            pos, rot = rigid_frames(mesh.vertices, ep.x[:, slices[name]])
            out.append((name, mesh, pos, rot))
    for body, held in scene.held.items():
        name = body.removeprefix("held_")
        if name in scene.objects:
            continue
        pose = np.asarray(ep.link_poses[:, scene.link_names.index(body)], np.float64)
        out.append((body, held.mesh, pose[:, :3], quat_matrices(pose[:, 3:])))
    return out


def table_distance(scene: Scene, x: np.ndarray) -> np.ndarray:
    """Exact signed distance [m] (negative inside) of points x (..., 3) to the table box."""
    return box_signed_distance(np.asarray(x, np.float64), np.asarray(scene.table.center_m, np.float64),
                               np.array([0.0, 0.0, 0.0, 1.0]), np.asarray(scene.table.half_extents_m, np.float64))


def table_and_robot_distance(scene: Scene, x: np.ndarray, link_poses: np.ndarray, reach_m: float = 0.0
                             ) -> np.ndarray:
    """(T, N) exact signed distance [m] (negative inside) of points x (T, N, 3) to the nearest of the table box
    and the robot's link boxes (finger pads included) posed by link_poses (T, L, 7) in scene.link_names order.
    Robot boxes farther than reach_m from every point of a frame are skipped, so values above reach_m may be
    a farther box's distance or +inf; the table is always exact."""
    x = np.asarray(x, np.float64)
    centre, quat, half = robot_boxes(scene, link_poses)
    return np.minimum(table_distance(scene, x), _min_box_distance(x, centre, quat, half, reach_m))


def penetration(scene: Scene, ep: Episode, cfg: ValidateConfig) -> int | None:
    """First frame with a cloth vertex deeper than penetration_tol_m inside the table, a robot link box
    or a rigid object (predicted or held; assumed convex, see convex_planes)."""
    x = ep.x[:, cloth_rows(scene)].astype(np.float64)
    if x.shape[1] == 0:
        return None
    deepest = -table_and_robot_distance(scene, x, ep.link_poses).min(axis=1)
    for name, mesh, pos, rot in rigid_poses(scene, ep):
        deepest = np.maximum(deepest, convex_depth(x, pos, rot, convex_planes(mesh.vertices, mesh.faces, name)))
    return _first(deepest > cfg.penetration_tol_m)


def self_intersection(scene: Scene, ep: Episode, cfg: ValidateConfig) -> int | None:
    """First checked frame (every self_intersection_every-th) where a cloth mesh edge crosses a
    non-adjacent triangle of the same mesh (one grouped BVH over the checked frames on validate.device,
    see self_intersection.py)."""
    slices = scene.vertex_slices()
    cloth = [(slices[n], m.faces, unique_edges(m.faces)) for n, m in scene.objects.items()
             if scene.object_kinds[n] == "cloth"]
    device = resolve_warp_device(cfg.device, "validate.device") if cloth else "cpu"
    checked = np.arange(0, len(ep.x), cfg.self_intersection_every)
    first = [first_crossing_frame(ep.x[checked][:, sl], faces, edges, device) for sl, faces, edges in cloth]
    hits = [checked[k] for k in first if k is not None]
    return int(min(hits)) if hits else None


def finger_pad_boxes(scene: Scene, link_poses: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World pad boxes of one arm's two fingers: centres (T, 2, 3), quats (T, 2, 4), half extents (2, 3)."""
    cols = [scene.link_names.index(f"{side}_{f}") for f in ("finger_a", "finger_b")]
    body = np.asarray(link_poses, np.float64)[:, cols]
    local = np.array([PAD_CENTRE_IN_FINGER_M["finger_a"], PAD_CENTRE_IN_FINGER_M["finger_b"]], np.float64)
    centre = body[..., :3] + quat_rotate(body[..., 3:], local[None])
    return centre, body[..., 3:], np.tile(np.asarray(PAD_HALF_EXTENTS_M, np.float64), (2, 1))


def adhesion(scene: Scene, ep: Episode, cfg: ValidateConfig) -> int | None:
    """Spurious gripper-bag adhesion after a release.

    A release is a frame r where an arm's opening (action d_L / d_R) rises past release_opening_m.
    The cloth vertices within adhesion_radius_m of that arm's pad boxes at r are watched; at
    w = r + round(adhesion_window_s / frame_dt_s) the episode fails (at frame w) if the pads rose more
    than adhesion_rise_m and a watched vertex rose more than adhesion_rise_m too while staying
    within adhesion_radius_m of the pads, i.e. it keeps following the open fingers. Releases whose
    window ends after the last frame are not judged.
    """
    x = ep.x[:, cloth_rows(scene)].astype(np.float64)
    window = max(1, int(round(cfg.adhesion_window_s / ep.frame_dt_s)))
    failures = []
    for side, col in OPENING_COLUMNS.items():
        opening = ep.action[:, col]
        releases = np.flatnonzero((opening[1:] > cfg.release_opening_m) & (opening[:-1] <= cfg.release_opening_m)) + 1
        centre, quat, half = finger_pad_boxes(scene, ep.link_poses, side)
        for r in releases:
            w = r + window
            if w >= len(x):
                continue
            near_r = _min_box_distance(x[[r]], centre[[r]], quat[[r]], half)[0] < cfg.adhesion_radius_m
            if not near_r.any():
                continue
            fingers_rise = (centre[w, :, 2] - centre[r, :, 2]).mean()
            near_w = _min_box_distance(x[[w]], centre[[w]], quat[[w]], half)[0] < cfg.adhesion_radius_m
            rose = x[w, :, 2] - x[r, :, 2] > cfg.adhesion_rise_m
            if fingers_rise > cfg.adhesion_rise_m and (near_r & near_w & rose).any():
                failures.append(int(w))
    return min(failures) if failures else None


def workspace(scene: Scene, ep: Episode, cfg: ValidateConfig) -> int | None:
    """First frame with a cloth vertex outside the axis-aligned workspace box."""
    x = ep.x[:, cloth_rows(scene)]
    out = (x < np.asarray(cfg.workspace_min_m)) | (x > np.asarray(cfg.workspace_max_m))
    return _first(out.any(axis=(1, 2)))


def visible_fraction(scene: Scene, x: np.ndarray, link_poses: np.ndarray, camera: str) -> np.ndarray:
    """(T,) fraction of points x (T, N, 3) that project inside the camera's image (in front of it)."""
    cam = scene.cameras[camera]
    K = intrinsics(cam)
    if x.shape[1] == 0:
        return np.ones(len(x))
    eye, rot = camera_pose(cam, scene.link_names, link_poses)  # (T, 3), (T, 3, 3)
    p = np.einsum("tni,tij->tnj", np.asarray(x, np.float64) - eye[:, None], rot)  # camera frame, OpenGL: looks down -z
    depth = -p[..., 2]
    front = depth > 1e-9
    safe = np.where(front, depth, 1.0)
    u = K[0, 0] * p[..., 0] / safe + K[0, 2]
    v = K[1, 2] - K[1, 1] * p[..., 1] / safe  # image rows grow downwards
    inside = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return inside.mean(axis=1)


def out_of_view(scene: Scene, ep: Episode, cfg: ValidateConfig) -> int | None:
    """First frame where less than min_visible_fraction of the cloth vertices are in the view camera's image."""
    frac = visible_fraction(scene, ep.x[:, cloth_rows(scene)], ep.link_poses, cfg.view_camera)
    return _first(frac < cfg.min_visible_fraction)


Predicate = Callable[[Scene, Episode, ValidateConfig], "int | None"]
PREDICATES: dict[str, Predicate] = {
    "non_finite": non_finite,
    "blow_up": blow_up,
    "penetration": penetration,
    "self_intersection": self_intersection,
    "adhesion": adhesion,
    "workspace": workspace,
    "out_of_view": out_of_view,
}


def first_failure(scene: Scene, x: np.ndarray, v: np.ndarray, action: np.ndarray, link_poses: np.ndarray,
                  config: ValidateConfig, *, frame_dt_s: float) -> tuple[str, int] | None:
    """(predicate name, first failing frame) of the first predicate in PREDICATES order that fails, or None.

    x, v (T, N_total, 3); action (T, 14); link_poses (T, L, 7) as in the trajectory store; frame_dt_s
    is the recorded frame interval (the store's dt), used by the adhesion window.
    """
    if not frame_dt_s > 0:
        raise ValueError(f"frame_dt_s must be positive, got {frame_dt_s}")
    ep = Episode(np.asarray(x), np.asarray(v), np.asarray(action), np.asarray(link_poses), float(frame_dt_s))
    for name, predicate in PREDICATES.items():
        frame = predicate(scene, ep, config)
        if frame is not None:
            return name, frame
    return None
