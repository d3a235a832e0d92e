"""Surface meshes of the rigid objects: a sphere and a cube, closed with outward normals, centred at the origin."""

from __future__ import annotations

import math

import numpy as np
import trimesh

from wc.scene.mesh import ObjectMesh, check_mesh, grid_faces, lumped_vertex_areas

MIN_SPHERE_VERTICES = 12
MIN_CUBE_VERTICES = 8

# Cube faces as (u axis, v axis) with u x v = outward normal, and the (u, v) offset of each face in the
# unfolded pattern, in units of the edge length: the four sides in a band (front -y, +x, back +y, -x),
# the top above the front and the bottom below it, so that the band and the front's top and bottom
# edges are continuous in uv.
_CUBE_FACES: tuple[tuple[tuple[int, ...], tuple[int, ...], tuple[int, int]], ...] = (
    ((1, 0, 0), (0, 0, 1), (0, 0)),  # front (-y)
    ((0, 1, 0), (0, 0, 1), (1, 0)),  # +x
    ((-1, 0, 0), (0, 0, 1), (2, 0)),  # back (+y)
    ((0, -1, 0), (0, 0, 1), (3, 0)),  # -x
    ((1, 0, 0), (0, 1, 0), (0, 1)),  # top (+z)
    ((1, 0, 0), (0, -1, 0), (0, -1)),  # bottom (-z)
)


def _fibonacci_sphere(n: int) -> np.ndarray:
    """n near-uniform unit vectors (n, 3) on a golden-angle spiral (no point at the poles)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    lon = math.pi * (1.0 + math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(lon), r * np.sin(lon), z], axis=1)


def make_sphere(radius_m: float, target_vertices: int, tag: int) -> ObjectMesh:
    """Sphere of `radius_m` with exactly `target_vertices` vertices (paper: 951).

    Vertices lie on a Fibonacci spiral, faces are their convex hull (near-equilateral triangles at
    any count, unlike an icosphere's 10*4^k + 2). rest_uv = radius * (longitude, latitude), m; seam
    at longitude +-pi.
    """
    if not (math.isfinite(radius_m) and radius_m > 0):
        raise ValueError(f"make_sphere: radius_m must be positive and finite, got {radius_m}")
    if int(target_vertices) != target_vertices or target_vertices < MIN_SPHERE_VERTICES:
        raise ValueError(f"make_sphere: target_vertices must be an integer >= {MIN_SPHERE_VERTICES}, "
                         f"got {target_vertices}")
    hull = trimesh.convex.convex_hull(_fibonacci_sphere(int(target_vertices)))
    unit = np.asarray(hull.vertices)
    if len(unit) != target_vertices:
        raise ValueError(f"make_sphere: convex hull kept {len(unit)} of {target_vertices} points")
    vertices, faces = radius_m * unit, np.asarray(hull.faces)
    uv = radius_m * np.stack([np.arctan2(unit[:, 1], unit[:, 0]), np.arcsin(np.clip(unit[:, 2], -1, 1))], axis=1)
    mesh = ObjectMesh(name="sphere", vertices=vertices, faces=faces, rest_uv=uv,
                      vertex_area=lumped_vertex_areas(vertices, faces), tag=tag)
    check_mesh(mesh, closed=True)
    return mesh


def make_cube(half_extent_m: float, target_vertices: int, tag: int) -> ObjectMesh:
    """Cube [-half_extent, half_extent]^3 with n segments per edge, n chosen so that 6 n^2 + 2 vertices
    is nearest `target_vertices` (paper: 465 -> n = 9, 488 vertices).

    rest_uv is a cube-map unfold in metres (see _CUBE_FACES); a vertex shared by several faces takes
    the uv of the first face listed, so uv has seams along the other cube edges.
    """
    if not (math.isfinite(half_extent_m) and half_extent_m > 0):
        raise ValueError(f"make_cube: half_extent_m must be positive and finite, got {half_extent_m}")
    if int(target_vertices) != target_vertices or target_vertices < MIN_CUBE_VERTICES:
        raise ValueError(f"make_cube: target_vertices must be an integer >= {MIN_CUBE_VERTICES}, "
                         f"got {target_vertices}")
    n = max(1, round(math.sqrt((target_vertices - 2) / 6)))
    steps = 2 * np.arange(n + 1) - n  # integer lattice coordinates of the grid lines, in [-n, n]
    index: dict[tuple[int, int, int], int] = {}
    xyz: list[tuple[int, int, int]] = []
    uv: list[tuple[float, float]] = []
    faces = []
    edge = 2 * half_extent_m
    for u_axis, v_axis, (ou, ov) in _CUBE_FACES:
        u_ax, v_ax = np.array(u_axis), np.array(v_axis)
        normal = np.cross(u_ax, v_ax)
        grid = np.empty((n + 1, n + 1), dtype=np.int64)
        for i, a in enumerate(steps):
            for j, b in enumerate(steps):
                key = tuple(int(c) for c in a * u_ax + b * v_ax + n * normal)
                if key not in index:
                    index[key] = len(xyz)
                    xyz.append(key)
                    uv.append((edge * (ou + (a + n) / (2 * n)), edge * (ov + (b + n) / (2 * n))))
                grid[i, j] = index[key]
        faces.append(grid_faces(grid))
    vertices = half_extent_m / n * np.array(xyz, dtype=np.float64)
    faces_arr = np.concatenate(faces)
    mesh = ObjectMesh(name="cube", vertices=vertices, faces=faces_arr, rest_uv=np.array(uv),
                      vertex_area=lumped_vertex_areas(vertices, faces_arr), tag=tag)
    check_mesh(mesh, closed=True)
    return mesh
