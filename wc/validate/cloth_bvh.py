"""Cloth self-proximity and self-crossing queries on a batch of states, through one grouped warp BVH per batch.

A batch holds B states of a scene's cloth (the frames of one episode for the validate check, the episodes of a batch
for the expansion's projection and checks). The triangles and the edges of every state go into one grouped BVH each
(group = state x cloth mesh, so a query never leaves its own state and mesh), built once and refitted as the states
change: no host sync, capturable in a CUDA graph. Queries write into preallocated device arrays:

- `crossings`: every edge against the triangles of its mesh that do not share a vertex with it, an exact
  segment-triangle test (the self-intersection check of wc.validate.predicates, and the expansion's rollback guard);
- `vertex_face_pairs` / `edge_edge_pairs`: for each cloth vertex (edge), up to K non-adjacent triangles (edges) closer
  than the sum of their reaches; a state whose lists overflowed is flagged.
States with a non-finite vertex take part in nothing (their bounds are parked far away).
"""

from __future__ import annotations

import numpy as np
import torch
import wc.warp_settings  # noqa: F401  (first: kernels take warp's settings when defined)
import warp as wp

FAR = wp.constant(1.0e6)  # where the bounds of a non-finite element are parked [m]
PAD_M = 1.0e-6  # bounds grown by this: a touching pair is still a candidate


@wp.func
def triangle_distance(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """Distance from p to the triangle abc (Ericson, Real-Time Collision Detection 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    q = a
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.length(p - a)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.length(p - b)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        q = a + ab * (d1 / (d1 - d3))
        return wp.length(p - q)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.length(p - c)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        q = a + ac * (d2 / (d2 - d6))
        return wp.length(p - q)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        q = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        return wp.length(p - q)
    denom = 1.0 / (va + vb + vc)
    q = a + ab * (vb * denom) + ac * (vc * denom)
    return wp.length(p - q)


@wp.func
def segment_crosses_triangle(p: wp.vec3, q: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> bool:
    """The segment p-q meets the triangle abc (Moeller-Trumbore; touching, at a boundary or in the plane, does not count)."""
    e1 = b - a
    e2 = c - a
    d = q - p
    h = wp.cross(d, e2)
    det = wp.dot(e1, h)
    if wp.abs(det) <= 1.0e-12 * wp.length(e1) * wp.length(e2) * wp.length(d) or det == 0.0:
        return False
    inv = 1.0 / det
    s = p - a
    u = inv * wp.dot(s, h)
    r = wp.cross(s, e1)
    w = inv * wp.dot(d, r)
    t = inv * wp.dot(e2, r)
    return u > 0.0 and w > 0.0 and u + w < 1.0 and t > 0.0 and t < 1.0


@wp.kernel
def _face_bounds(x: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.vec3i), rows: int, nf: int,
                 lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    b = tid // nf
    f = faces[tid - b * nf]
    p0 = x[b * rows + f[0]]
    p1 = x[b * rows + f[1]]
    p2 = x[b * rows + f[2]]
    lo = wp.min(wp.min(p0, p1), p2) - wp.vec3(PAD_M)
    hi = wp.max(wp.max(p0, p1), p2) + wp.vec3(PAD_M)
    if not (wp.isfinite(lo) and wp.isfinite(hi)):
        lo = wp.vec3(FAR)
        hi = wp.vec3(FAR)
    lowers[tid] = lo
    uppers[tid] = hi


@wp.kernel
def _edge_bounds(x: wp.array(dtype=wp.vec3), edges: wp.array(dtype=wp.vec2i), rows: int, ne: int,
                 lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    b = tid // ne
    e = edges[tid - b * ne]
    p = x[b * rows + e[0]]
    q = x[b * rows + e[1]]
    lo = wp.min(p, q) - wp.vec3(PAD_M)
    hi = wp.max(p, q) + wp.vec3(PAD_M)
    if not (wp.isfinite(lo) and wp.isfinite(hi)):
        lo = wp.vec3(FAR)
        hi = wp.vec3(FAR)
    lowers[tid] = lo
    uppers[tid] = hi


@wp.kernel
def _edge_crossings(x: wp.array(dtype=wp.vec3), edges: wp.array(dtype=wp.vec2i), edge_group: wp.array(dtype=int),
                    faces: wp.array(dtype=wp.vec3i), rows: int, ne: int, nf: int, bvh: wp.uint64,
                    involved: wp.array(dtype=wp.int32), crossing: wp.array(dtype=wp.int32),
                    hit_face: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    b = tid // ne
    e = edges[tid - b * ne]
    base = b * rows
    p = x[base + e[0]]
    q = x[base + e[1]]
    hit_face[tid] = -1
    if not (wp.isfinite(p) and wp.isfinite(q)):
        return
    root = wp.bvh_get_group_root(bvh, edge_group[tid])
    query = wp.bvh_query_aabb(bvh, wp.min(p, q) - wp.vec3(PAD_M), wp.max(p, q) + wp.vec3(PAD_M), root)
    item = int(0)
    while wp.bvh_query_next(query, item):
        fi = item - b * nf
        if fi < 0 or fi >= nf:
            continue
        f = faces[fi]
        if f[0] == e[0] or f[1] == e[0] or f[2] == e[0] or f[0] == e[1] or f[1] == e[1] or f[2] == e[1]:
            continue
        if segment_crosses_triangle(p, q, x[base + f[0]], x[base + f[1]], x[base + f[2]]):
            hit_face[tid] = fi
            crossing[b] = 1
            involved[base + e[0]] = 1
            involved[base + e[1]] = 1
            involved[base + f[0]] = 1
            involved[base + f[1]] = 1
            involved[base + f[2]] = 1


@wp.kernel
def _vertex_face_pairs(x: wp.array(dtype=wp.vec3), vertices: wp.array(dtype=int), vertex_group: wp.array(dtype=int),
                       faces: wp.array(dtype=wp.vec3i), rows: int, nv: int, nf: int, bvh: wp.uint64,
                       reach: wp.array(dtype=float), face_reach: wp.array(dtype=float),
                       max_face_reach: wp.array(dtype=float), skip_start: wp.array(dtype=int),
                       skip_rows: wp.array(dtype=int), pairs: wp.array2d(dtype=int), dropped: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    b = tid // nv
    i = tid - b * nv
    base = b * rows
    row = vertices[i]
    cap = pairs.shape[1]
    for k in range(cap):
        pairs[tid, k] = -1
    p = x[base + row]
    r = reach[tid]
    if not (wp.isfinite(p) and r >= 0.0):
        return
    box = wp.vec3(r + max_face_reach[b] + PAD_M)
    root = wp.bvh_get_group_root(bvh, vertex_group[tid])
    query = wp.bvh_query_aabb(bvh, p - box, p + box, root)
    item = int(0)
    n = int(0)
    while wp.bvh_query_next(query, item):
        fi = item - b * nf
        if fi < 0 or fi >= nf:
            continue
        f = faces[fi]
        skip = bool(False)
        for s in range(skip_start[i], skip_start[i + 1]):
            if skip_rows[s] == f[0] or skip_rows[s] == f[1] or skip_rows[s] == f[2]:
                skip = True
        if skip:
            continue
        if triangle_distance(p, x[base + f[0]], x[base + f[1]], x[base + f[2]]) < r + face_reach[b * nf + fi]:
            if n < cap:
                pairs[tid, n] = fi
                n += 1
            else:
                dropped[b] = 1


@wp.kernel
def _edge_edge_pairs(x: wp.array(dtype=wp.vec3), edges: wp.array(dtype=wp.vec2i), edge_group: wp.array(dtype=int),
                     rows: int, ne: int, bvh: wp.uint64, reach: wp.array(dtype=float),
                     max_reach: wp.array(dtype=float), pairs: wp.array2d(dtype=int), dropped: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    b = tid // ne
    ei = tid - b * ne
    e = edges[ei]
    base = b * rows
    cap = pairs.shape[1]
    for k in range(cap):
        pairs[tid, k] = -1
    p = x[base + e[0]]
    q = x[base + e[1]]
    r = reach[tid]
    if not (wp.isfinite(p) and wp.isfinite(q) and r >= 0.0):
        return
    box = wp.vec3(r + max_reach[b] + PAD_M)
    root = wp.bvh_get_group_root(bvh, edge_group[tid])
    query = wp.bvh_query_aabb(bvh, wp.min(p, q) - box, wp.max(p, q) + box, root)
    item = int(0)
    n = int(0)
    while wp.bvh_query_next(query, item):
        ki = item - b * ne
        if ki <= ei or ki >= ne:
            continue
        o = edges[ki]
        if o[0] == e[0] or o[0] == e[1] or o[1] == e[0] or o[1] == e[1]:
            continue
        d = wp.closest_point_edge_edge(p, q, x[base + o[0]], x[base + o[1]], 1.0e-20)[2]
        if d < r + reach[b * ne + ki]:
            if n < cap:
                pairs[tid, n] = ki
                n += 1
            else:
                dropped[b] = 1


def _wp(t: torch.Tensor, dtype=None):  # noqa: ANN001, ANN202 - a warp view of a contiguous torch tensor
    return wp.from_torch(t.contiguous(), dtype=dtype, requires_grad=False)


class ClothBVH:
    """The grouped triangle and edge BVHs of B states (N rows each) of cloth meshes (module docstring).

    faces (F, 3), edges (E, 2), vertices (V,): element rows in a state; face_mesh (F,), edge_mesh (E,), vertex_mesh
    (V,): their cloth mesh (0 .. meshes-1). Arrays live on `x`'s device (torch CPU or CUDA) in every call.
    """

    def __init__(self, x: torch.Tensor, faces: torch.Tensor, face_mesh: torch.Tensor, edges: torch.Tensor,
                 edge_mesh: torch.Tensor, vertices: torch.Tensor, vertex_mesh: torch.Tensor, meshes: int) -> None:
        wp.init()
        self._streams: dict[int, wp.Stream] = {}
        dev = x.device
        self.batch, self.rows = int(x.shape[0]), int(x.shape[1])
        self.nf, self.ne, self.nv = len(faces), len(edges), len(vertices)
        self.device = wp.device_from_torch(dev)
        i32 = dict(dtype=torch.int32, device=dev)
        self.faces = _wp(faces.to(**i32), wp.vec3i)
        self.edges = _wp(edges.to(**i32), wp.vec2i)
        self.vertices = _wp(vertices.to(**i32))
        first = torch.arange(self.batch, device=dev)[:, None] * meshes

        def groups(mesh: torch.Tensor) -> torch.Tensor:
            return (first + mesh.to(dev)[None]).reshape(-1).to(torch.int32).contiguous()

        self._face_group, self._edge_group, self._vertex_group = groups(face_mesh), groups(edge_mesh), groups(vertex_mesh)
        self.face_group, self.edge_group = _wp(self._face_group), _wp(self._edge_group)
        self.vertex_group = _wp(self._vertex_group)
        self._bounds = {k: (torch.zeros(n * self.batch, 3, dtype=torch.float32, device=dev),
                            torch.zeros(n * self.batch, 3, dtype=torch.float32, device=dev))
                        for k, n in (("faces", self.nf), ("edges", self.ne))}
        self._fill_bounds(x)
        with wp.ScopedDevice(self.device):
            self.face_bvh = wp.Bvh(_wp(self._bounds["faces"][0], wp.vec3), _wp(self._bounds["faces"][1], wp.vec3),
                                   groups=self.face_group) if self.nf else None
            self.edge_bvh = wp.Bvh(_wp(self._bounds["edges"][0], wp.vec3), _wp(self._bounds["edges"][1], wp.vec3),
                                   groups=self.edge_group) if self.ne else None

    def _stream(self):  # noqa: ANN202 - warp launches on torch's current stream (a CUDA graph capture records them)
        if not self.device.is_cuda:
            return wp.ScopedDevice(self.device)
        current = torch.cuda.current_stream(self.device.ordinal)
        if current.cuda_stream not in self._streams:
            self._streams[current.cuda_stream] = wp.stream_from_torch(current)
        # no event wait on warp's own stream: that stream is not part of a capture
        return wp.ScopedStream(self._streams[current.cuda_stream], sync_enter=False)

    def _points(self, x: torch.Tensor):  # noqa: ANN202
        if tuple(x.shape) != (self.batch, self.rows, 3) or x.dtype != torch.float32:
            raise ValueError(f"cloth BVH: states must be float32 ({self.batch}, {self.rows}, 3), got "
                             f"{x.dtype} {tuple(x.shape)}")
        return _wp(x.reshape(-1, 3), wp.vec3)

    def _fill_bounds(self, x: torch.Tensor) -> None:
        pts = self._points(x)
        with self._stream():
            for key, kernel, items, n in (("faces", _face_bounds, self.faces, self.nf),
                                          ("edges", _edge_bounds, self.edges, self.ne)):
                if n:
                    lo, hi = self._bounds[key]
                    wp.launch(kernel, dim=n * self.batch, inputs=[pts, items, self.rows, n],
                              outputs=[_wp(lo, wp.vec3), _wp(hi, wp.vec3)], device=self.device)

    def refit(self, x: torch.Tensor) -> None:
        """Bounds of states x (B, N, 3) and both trees refitted to them (topology kept)."""
        self._fill_bounds(x)
        with self._stream():
            for tree in (self.face_bvh, self.edge_bvh):
                if tree is not None:
                    tree.refit()

    def rebuild(self, x: torch.Tensor) -> None:
        """As `refit`, with both hierarchies built anew (after the states changed wholesale)."""
        self._fill_bounds(x)
        with self._stream():
            for tree in (self.face_bvh, self.edge_bvh):
                if tree is not None:
                    tree.rebuild()

    def crossings(self, x: torch.Tensor, involved: torch.Tensor, crossing: torch.Tensor, hit_face: torch.Tensor
                  ) -> None:
        """Into involved (B, N) int32 (rows on a crossing edge or crossed triangle set to 1), crossing (B,) int32 and
        hit_face (B, E) int32 (a crossed triangle per edge, -1 none) for states x that the trees were refitted to;
        the caller zeroes involved and crossing first."""
        if not self.ne or not self.nf:
            hit_face.fill_(-1)
            return
        with self._stream():
            wp.launch(_edge_crossings, dim=self.ne * self.batch,
                      inputs=[self._points(x), self.edges, self.edge_group, self.faces, self.rows, self.ne, self.nf,
                              self.face_bvh.id],
                      outputs=[_wp(involved.view(-1)), _wp(crossing), _wp(hit_face.view(-1))], device=self.device)

    def vertex_face_pairs(self, x: torch.Tensor, reach: torch.Tensor, face_reach: torch.Tensor,
                          skip: tuple[torch.Tensor, torch.Tensor], pairs: torch.Tensor, dropped: torch.Tensor) -> None:
        """Into pairs (B, V, K) int32 (-1: empty) the triangles of each cloth vertex's mesh closer than reach (B, V) +
        face_reach (B, F) [m], skipping those with a corner in the vertex's skip rows (CSR start (V + 1,), rows);
        dropped (B,) int32 set to 1 where a list overflowed (the caller zeroes it)."""
        max_face = face_reach.amax(dim=1) if face_reach.shape[1] else face_reach.new_zeros(self.batch)
        with self._stream():
            wp.launch(_vertex_face_pairs, dim=self.nv * self.batch,
                      inputs=[self._points(x), self.vertices, self.vertex_group, self.faces, self.rows, self.nv,
                              self.nf, self.face_bvh.id, _wp(reach.reshape(-1)), _wp(face_reach.reshape(-1)),
                              _wp(max_face), _wp(skip[0]), _wp(skip[1])],
                      outputs=[_wp(pairs.view(-1, pairs.shape[-1])), _wp(dropped)], device=self.device)

    def edge_edge_pairs(self, x: torch.Tensor, reach: torch.Tensor, pairs: torch.Tensor, dropped: torch.Tensor) -> None:
        """Into pairs (B, E, K) int32 (-1: empty) the later edges (index > own) of each edge's mesh, sharing no
        vertex with it, closer than the sum of their reaches (B, E) [m]; dropped as `vertex_face_pairs`."""
        with self._stream():
            wp.launch(_edge_edge_pairs, dim=self.ne * self.batch,
                      inputs=[self._points(x), self.edges, self.edge_group, self.rows, self.ne, self.edge_bvh.id,
                              _wp(reach.reshape(-1)), _wp(reach.amax(dim=1))],
                      outputs=[_wp(pairs.view(-1, pairs.shape[-1])), _wp(dropped)], device=self.device)


def crossing_faces(points: np.ndarray, faces: np.ndarray, edges: np.ndarray, device: str = "cpu") -> np.ndarray:
    """(B, E) index of a non-adjacent face each edge crosses, or -1, for states points (B, N, 3) [m] of one cloth mesh
    with faces (F, 3) and edges (E, 2) (each once)."""
    dev = torch.device("cuda", int(device.split(":")[1]) if ":" in device else 0) if device.startswith("cuda") \
        else torch.device("cpu")
    x = torch.as_tensor(np.ascontiguousarray(points, np.float32), device=dev)
    f = torch.as_tensor(np.asarray(faces, np.int64), device=dev)
    e = torch.as_tensor(np.asarray(edges, np.int64), device=dev)
    zeros = torch.zeros
    bvh = ClothBVH(x, f, zeros(len(f), dtype=torch.long), e, zeros(len(e), dtype=torch.long),
                   zeros(0, dtype=torch.long), zeros(0, dtype=torch.long), 1)
    involved = zeros(x.shape[:2], dtype=torch.int32, device=dev)
    crossing = zeros(x.shape[0], dtype=torch.int32, device=dev)
    hit = torch.full((x.shape[0], len(e)), -1, dtype=torch.int32, device=dev)
    bvh.crossings(x, involved, crossing, hit)
    return hit.cpu().numpy()
