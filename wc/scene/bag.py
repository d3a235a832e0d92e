"""Procedural T-shirt-style shopping bag: an open-top rectangular tube, a flat bottom and two arched
handle straps, one structured grid per piece, stitched by sharing vertices.

Rest shape: standing upright, bottom at z = 0, centred at x = y = 0; x = width, y = depth (front face
at y = -depth/2, back at +depth/2), z up. Normals point out of the bag.

rest_uv is a sewing pattern in metres, isometric within each piece:
  tube     (arc length around the perimeter from the seam, z); the seam runs down the middle of the
           +x side gusset and the perimeter runs counter-clockwise seen from above;
  bottom   below the front face: (the front face's u at x, -(y + depth/2)), v in [-depth, 0];
  handles  continue the front face upward: (the front face's u at x, height + arc length along the arch).
Shared vertices keep the tube's uv, so across the seams (the tube seam column, each handle's back
junction, the bottom's back and side edges) uv-near is not mesh-near; those vertices form the group
`uv_seam`, and an edge whose ends are both off it lies inside one piece.

Groups: body (the tube, incl. rim and bottom ring), rim (top ring), bottom (bottom grid incl. the
bottom ring), handle_0 (+x end) and handle_1 (-x end) (strap incl. the shared rim vertices), uv_seam.
Attributes: part (int32: 0 body/bottom, 1 handle_0, 2 handle_1; shared rim vertices belong to their
handle), handle_s (float32, 0 at the front rim -> 1 at the back rim along the arch, -1 off the
handles), handle_u (float32, 0 at the strap's inner edge -> 1 at its outer edge x = +-width/2, -1 off).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from wc.scene.mesh import ObjectMesh, VertexPool, check_mesh, grid_faces, lumped_vertex_areas

MIN_BAG_VERTICES = 100  # below this the coarsest grid (every dimension 2 segments) no longer fits
VERTEX_COUNT_TOLERANCE = 0.15  # relative; make_bag raises if the snapped grid misses the target by more
_ARCH_SAMPLES = 4097  # dense polyline used to parametrise the arch by arc length
_EDGE_SEARCH_SPAN = 2.0  # the edge length is searched in [h0 / span, h0 * span] ...
_EDGE_SEARCH_STEPS = 801  # ... on a log grid of this many values
_COUNT_SLACK = 0.02  # relative vertex-count error below which grids rank by uniformity alone


@dataclass(frozen=True)
class BagGrid:
    """Segment counts of the bag's grids; every count >= 2; `n_depth` is even (the seam is at its middle)
    and so is `n_arch` (a row of vertices at the top of each arch, handle_s = 0.5)."""

    n_handle: int  # across each handle strap (along x)
    n_mouth: int  # along the front/back face between the straps
    n_depth: int  # across each side gusset
    n_height: int  # up the tube
    n_arch: int  # along each handle arch

    @property
    def n_width(self) -> int:
        return 2 * self.n_handle + self.n_mouth

    @property
    def n_ring(self) -> int:
        return 2 * (self.n_width + self.n_depth)

    @property
    def num_vertices(self) -> int:
        return (self.n_ring * (self.n_height + 1) + (self.n_width - 1) * (self.n_depth - 1)
                + 2 * (self.n_handle + 1) * (self.n_arch - 1))

    @classmethod
    def for_edge_length(cls, h_m: float, width_m: float, depth_m: float, height_m: float,
                        handle_width_m: float, arch_length_m: float) -> BagGrid:
        """Each dimension snapped to the nearest whole number of segments of length ~h_m."""
        def segments(length_m: float) -> int:
            return max(2, round(length_m / h_m))

        return cls(n_handle=segments(handle_width_m), n_mouth=segments(width_m - 2 * handle_width_m),
                   n_depth=2 * max(1, round(depth_m / (2 * h_m))), n_height=segments(height_m),
                   n_arch=2 * max(1, round(arch_length_m / (2 * h_m))))


def _arch(depth_m: float, rise_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Semi-ellipse y = -depth/2 cos(t), dz = rise sin(t), t in [0, pi], densely sampled.

    Returns t (K,) and the arc length s (K,) m at each sample; the legs leave the rim vertically.
    """
    t = np.linspace(0.0, math.pi, _ARCH_SAMPLES)
    yz = np.stack([-0.5 * depth_m * np.cos(t), rise_m * np.sin(t)], axis=1)
    return t, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(yz, axis=0), axis=1))])


def choose_bag_grid(target_vertices: int, width_m: float, depth_m: float, height_m: float,
                    handle_width_m: float, handle_rise_m: float) -> BagGrid:
    """The most uniform grid whose vertex count is near `target_vertices`.

    Start from the edge length h0 = sqrt(surface area / target) (a square grid has one vertex per
    h^2) and search h on a log grid around h0, because snapping each dimension to whole segments
    moves the count in steps; at coarse targets the tube may also get one row more or fewer than
    its h asks for, to fill the gaps between those steps. Ranking: counts within _COUNT_SLACK of the
    target are equally good; then no extra row beats one; then h nearest h0.
    """
    arch_length = _arch(depth_m, handle_rise_m)[1][-1]
    area = 2 * (width_m + depth_m) * height_m + width_m * depth_m + 2 * handle_width_m * arch_length
    h0 = math.sqrt(area / target_vertices)
    best: tuple[tuple[float, int, float], BagGrid] | None = None
    for h in h0 * np.geomspace(1 / _EDGE_SEARCH_SPAN, _EDGE_SEARCH_SPAN, _EDGE_SEARCH_STEPS):
        base = BagGrid.for_edge_length(h, width_m, depth_m, height_m, handle_width_m, arch_length)
        for extra_rows in (0, -1, 1):
            grid = replace(base, n_height=max(2, base.n_height + extra_rows))
            error = abs(grid.num_vertices - target_vertices) / target_vertices
            key = (max(error, _COUNT_SLACK), abs(extra_rows), abs(math.log(h / h0)))
            if best is None or key < best[0]:
                best = (key, grid)
    assert best is not None
    return best[1]


def make_bag(target_vertices: int, width_m: float, depth_m: float, height_m: float,
             handle_width_m: float, handle_rise_m: float, tag: int) -> ObjectMesh:
    """The bag mesh with about `target_vertices` vertices (within VERTEX_COUNT_TOLERANCE)."""
    dims = dict(width_m=width_m, depth_m=depth_m, height_m=height_m, handle_width_m=handle_width_m,
                handle_rise_m=handle_rise_m)
    for key, value in dims.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"make_bag: {key} must be positive and finite, got {value}")
    if handle_width_m >= width_m / 2:
        raise ValueError(f"make_bag: handle_width_m ({handle_width_m}) must be < width_m / 2 ({width_m / 2}) "
                         "so that the mouth between the handles stays open")
    if int(target_vertices) != target_vertices or target_vertices < MIN_BAG_VERTICES:
        raise ValueError(f"make_bag: target_vertices must be an integer >= {MIN_BAG_VERTICES}, got {target_vertices}")
    grid = choose_bag_grid(int(target_vertices), **dims)
    if abs(grid.num_vertices - target_vertices) > VERTEX_COUNT_TOLERANCE * target_vertices:
        raise ValueError(f"make_bag: no grid within {VERTEX_COUNT_TOLERANCE:.0%} of {target_vertices} vertices for "
                         f"these dimensions (nearest: {grid.num_vertices}); change target_vertices or the aspect ratios")

    w2, d2, hw = width_m / 2, depth_m / 2, handle_width_m
    nh, nw, nd, nz, ring = grid.n_handle, grid.n_width, grid.n_depth, grid.n_height, grid.n_ring
    xs = np.concatenate([np.linspace(-w2, -w2 + hw, nh + 1), np.linspace(-w2 + hw, w2 - hw, grid.n_mouth + 1)[1:],
                         np.linspace(w2 - hw, w2, nh + 1)[1:]])  # (nw + 1,) front/back/bottom columns
    ys = np.linspace(-d2, d2, nd + 1)  # (nd + 1,) side/bottom rows
    ix, iy = np.arange(nw + 1), np.arange(nd + 1)

    # Ring position k of each perimeter sample; k = 0 is the seam (w2, 0), counter-clockwise from above:
    # +x side (y > 0) -> back (x decreasing) -> -x side (y decreasing) -> front (x increasing) -> +x side (y < 0).
    front_k = 3 * nd // 2 + nw + ix
    back_k = nd // 2 + nw - ix
    minus_k = nd // 2 + nw + nd - iy
    plus_k = (3 * nd // 2 + 2 * nw + iy) % ring
    ring_xy = np.empty((ring, 2))
    ring_xy[front_k] = np.stack([xs, np.full_like(xs, -d2)], 1)
    ring_xy[back_k] = np.stack([xs, np.full_like(xs, d2)], 1)
    ring_xy[minus_k] = np.stack([np.full_like(ys, -w2), ys], 1)
    ring_xy[plus_k] = np.stack([np.full_like(ys, w2), ys], 1)
    ring_u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ring_xy, axis=0), axis=1))])
    front_u = ring_u[front_k]

    pool = VertexPool()
    # Tube: vertex r * ring + k; the index grid repeats column k = 0 at the end to close the seam.
    zs = np.linspace(0.0, height_m, nz + 1)
    kk, zz = np.meshgrid(np.arange(ring), zs, indexing="xy")  # (nz + 1, ring)
    tube_ids = pool.add(np.stack([ring_xy[kk, 0], ring_xy[kk, 1], zz], -1), np.stack([ring_u[kk], zz], -1))
    tube_grid = np.concatenate([tube_ids, tube_ids[:, :1]], axis=1).T  # (ring + 1, nz + 1): (u, z)
    bottom_ring, top_ring = tube_ids[0], tube_ids[-1]

    # Bottom: (nw + 1, nd + 1) over (x, y); boundary entries are the tube's bottom ring.
    bottom_grid = np.empty((nw + 1, nd + 1), dtype=np.int64)
    bx, by = np.meshgrid(xs[1:-1], ys[1:-1], indexing="ij")
    bottom_grid[1:-1, 1:-1] = pool.add(np.stack([bx, by, np.zeros_like(bx)], -1),
                                       np.stack([np.broadcast_to(front_u[1:-1, None], bx.shape), -(by + d2)], -1))
    bottom_grid[:, 0], bottom_grid[:, -1] = bottom_ring[front_k], bottom_ring[back_k]
    bottom_grid[0, :], bottom_grid[-1, :] = bottom_ring[minus_k], bottom_ring[plus_k]

    # Handles: (nh + 1, n_arch + 1) over (x, arch); arch rows 0 and -1 are the front and back rim vertices.
    t_dense, s_dense = _arch(depth_m, handle_rise_m)
    s = np.linspace(0.0, s_dense[-1], grid.n_arch + 1)
    t = np.interp(s, s_dense, t_dense)
    arch_y, arch_z = -d2 * np.cos(t), height_m + handle_rise_m * np.sin(t)
    handle_cols = (np.arange(nw - nh, nw + 1), np.arange(0, nh + 1))  # handle_0 at +x, handle_1 at -x
    handle_grids, across = [], []  # across: distance from each column to the strap's inner edge, m
    for cols in handle_cols:
        hx, hs = np.meshgrid(xs[cols], s[1:-1], indexing="ij")
        hgrid = np.empty((nh + 1, grid.n_arch + 1), dtype=np.int64)
        hgrid[:, 1:-1] = pool.add(
            np.stack([hx, np.broadcast_to(arch_y[1:-1], hx.shape), np.broadcast_to(arch_z[1:-1], hx.shape)], -1),
            np.stack([np.broadcast_to(front_u[cols, None], hx.shape), height_m + hs], -1))
        hgrid[:, 0], hgrid[:, -1] = top_ring[front_k[cols]], top_ring[back_k[cols]]
        handle_grids.append(hgrid)
        across.append(np.abs(xs[cols]) - (w2 - hw))

    # Axis order (u, v) of each grid makes d/du x d/dv point out of the bag; the bottom's v runs to -y.
    faces = np.concatenate([grid_faces(tube_grid), grid_faces(bottom_grid[:, ::-1])]
                           + [grid_faces(g) for g in handle_grids])
    vertices, uv = pool.arrays()
    n = pool.count

    part = np.zeros(n, dtype=np.int32)
    handle_s = np.full(n, -1.0, dtype=np.float32)
    handle_u = np.full(n, -1.0, dtype=np.float32)
    groups = {"body": tube_ids.ravel(), "rim": top_ring, "bottom": np.unique(bottom_grid)}
    for h, (hgrid, dist) in enumerate(zip(handle_grids, across)):
        groups[f"handle_{h}"] = np.unique(hgrid)
        part[hgrid] = h + 1
        handle_s[hgrid] = (s / s[-1])[None, :]
        handle_u[hgrid] = (dist / hw)[:, None]
    groups["uv_seam"] = np.unique(np.concatenate(
        [tube_grid[0], bottom_grid[:, -1], bottom_grid[0, 1:], bottom_grid[-1, 1:]]
        + [g[:, -1] for g in handle_grids]))

    mesh = ObjectMesh(name="bag", vertices=vertices, faces=faces, rest_uv=uv,
                      vertex_area=lumped_vertex_areas(vertices, faces), tag=tag, groups=groups,
                      attributes={"part": part, "handle_s": handle_s, "handle_u": handle_u})
    check_mesh(mesh)
    return mesh
