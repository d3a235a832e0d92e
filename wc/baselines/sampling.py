"""Particles for the baselines: farthest-point samples of mesh vertices and tool points, and the map back.

The object particles are mesh vertices chosen by farthest-point sampling (FPS) under the rest
mesh's geodesic distance (shortest paths along rest edges, weighted by rest length): inside a
sewing-pattern piece this is the rest (u, v) distance (the pattern is isometric), and unlike plain
(u, v) distance it does not jump across the bag's seams. Every vertex then follows its k nearest
particles (same distance, same object) by inverse-square-distance weights on their displacement
since the first frame; a sampled vertex has weight 1 on itself, so the map is exact there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from wc.model.layout import SceneLayout

MAP_NEIGHBORS = 3  # particles each vertex follows


@dataclass
class ParticleMap:
    """K particles of N vertices and the interpolation of every vertex from them."""

    vertices: torch.Tensor  # (K,) long: the particles' vertex rows
    object_id: torch.Tensor  # (K,) long: object of each particle (layout.objects order)
    neighbors: torch.Tensor  # (N, k) long: particle indices each vertex follows
    weights: torch.Tensor  # (N, k) float32, rows sum to 1

    def to_vertices(self, x0: torch.Tensor, p0: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Vertex positions (B, S, N, 3) from particle positions p (B, S, K, 3), the first frame x0 (B, N, 3), p0 (B, K, 3)."""
        moved = (p - p0[:, None])[:, :, self.neighbors]  # (B, S, N, k, 3)
        return x0[:, None] + (self.weights[..., None] * moved).sum(-2)


def _rest_graph(layout: SceneLayout) -> coo_matrix:
    n = layout.num_vertices
    e = layout.edges.cpu().numpy()
    w = np.maximum(layout.rest_lengths.cpu().numpy().astype(np.float64), 1e-9)
    return coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()


def _allocate(sizes: np.ndarray, count: int) -> np.ndarray:
    """Particles per object: proportional to vertex count, at least 1, at most the object's vertices."""
    if count >= sizes.sum():
        return sizes.copy()
    k = np.clip(np.round(sizes * count / sizes.sum()).astype(int), 1, sizes)
    while k.sum() > count and (k > 1).any():
        k[np.argmax(np.where(k > 1, k, -1))] -= 1
    while k.sum() < count:
        k[np.argmax(sizes - k)] += 1
    return k


def particle_map(layout: SceneLayout, count: int, neighbors: int = MAP_NEIGHBORS) -> ParticleMap:
    """FPS of `count` particles over the layout's vertices (split by object size) and the map back (cached)."""
    key = f"baselines/particles/{count}/{neighbors}"
    if key in layout.cache:
        return layout.cache[key]
    if count < 1:
        raise ValueError(f"particle count must be >= 1, got {count}")
    graph = _rest_graph(layout)
    object_index = layout.object_index.cpu().numpy()
    sizes = np.bincount(object_index, minlength=len(layout.objects))
    chosen: list[int] = []
    for o, k in enumerate(_allocate(sizes, count)):
        rows = np.flatnonzero(object_index == o)
        # start from the vertex farthest from the object's first vertex (deterministic)
        dist = dijkstra(graph, indices=int(rows[0]))[rows]
        pick = [int(rows[np.argmax(np.where(np.isinf(dist), np.inf, dist))])]
        best = dijkstra(graph, indices=pick[0])[rows]
        for _ in range(int(k) - 1):
            pick.append(int(rows[np.argmax(best)]))
            best = np.minimum(best, dijkstra(graph, indices=pick[-1])[rows])
        chosen.extend(pick)
    particles = np.asarray(chosen)
    dist = dijkstra(graph, indices=particles).T  # (N, K): inf across objects and unreachable pieces
    k = min(neighbors, len(particles))
    order = np.argsort(dist, axis=1, kind="stable")[:, :k]
    d = np.take_along_axis(dist, order, axis=1)
    if np.isinf(d[:, 0]).any():
        bad = int(np.flatnonzero(np.isinf(d[:, 0]))[0])
        raise ValueError(f"vertex {bad} reaches no particle along rest edges: raise the particle count")
    w = np.where(np.isinf(d), 0.0, 1.0 / np.maximum(d, 1e-12) ** 2)
    w[d[:, 0] == 0.0] = np.eye(k)[0]  # a sampled vertex follows itself only
    w /= w.sum(1, keepdims=True)
    device = layout.attributes.device
    result = ParticleMap(torch.from_numpy(particles).to(device), torch.from_numpy(object_index[particles]).to(device),
                         torch.from_numpy(order).to(device), torch.from_numpy(w.astype(np.float32)).to(device))
    layout.cache[key] = result
    return result


def farthest_points(points: torch.Tensor, count: int) -> torch.Tensor:
    """Indices (min(count, M),) of a Euclidean FPS of points (M, 3), starting from the point farthest from the centroid."""
    m = points.shape[0]
    if count >= m:
        return torch.arange(m, device=points.device)
    p = points.detach().double()
    pick = [int((p - p.mean(0)).norm(dim=1).argmax())]
    best = (p - p[pick[0]]).norm(dim=1)
    for _ in range(count - 1):
        pick.append(int(best.argmax()))
        best = torch.minimum(best, (p - p[pick[-1]]).norm(dim=1))
    return torch.tensor(pick, device=points.device)
