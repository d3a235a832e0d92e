"""Neighbour search for the tokenizer: fixed-radius pairs (warp hash grid) and nearest points.

Positions are (N, 3) float32 tensors in metres; batch ids are (N,) int64 scene indices, so many
scenes can be searched in one call without mixing. Only indices come back: no gradient flows
through the search (the convolutions differentiate through the offsets they gather).
"""

from __future__ import annotations

import contextlib

import torch
import wc.warp_settings  # noqa: F401  (first: kernels take warp's settings when defined)
import warp as wp
from torch import Tensor

# Candidates are gathered with a slightly larger radius in warp and then filtered in torch, so the
# final test is one expression, `sum((p_j - q_i)^2) < radius^2` in float32 torch, identical to a brute
# force in torch whatever floating-point contraction warp's compiler applies.
_CANDIDATE_SLACK = 1.0e-4
_MAX_GRID_DIM = 128  # hash-grid cells per axis; the grid hashes, so this bounds memory, not extent
_MIN_GRID_DIM = 8
_CDIST_CHUNK_ELEMENTS = 1 << 24  # query rows x points per cdist call in nearest_index

_warp_ready = False


def _init_warp() -> None:
    """Initialise warp on first use (it prints a banner), not at import."""
    global _warp_ready
    if not _warp_ready:
        wp.init()
        _warp_ready = True


@wp.kernel
def _count_candidates(
    grid: wp.uint64,
    query: wp.array(dtype=wp.vec3),
    query_group: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
    radius: float,
    exclude_self: int,
    counts: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    q = query[i]
    r2 = radius * radius
    it = wp.hash_grid_query(grid, q, radius, int(query_group[i]))
    j = int(0)
    n = int(0)
    while wp.hash_grid_query_next(it, j):
        d = points[j] - q
        if wp.dot(d, d) < r2 and not (exclude_self != 0 and j == i):
            n += 1
    counts[i] = n


@wp.kernel
def _fill_candidates(
    grid: wp.uint64,
    query: wp.array(dtype=wp.vec3),
    query_group: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
    radius: float,
    exclude_self: int,
    starts: wp.array(dtype=wp.int64),
    out_j: wp.array(dtype=wp.int64),
):
    i = wp.tid()
    q = query[i]
    r2 = radius * radius
    it = wp.hash_grid_query(grid, q, radius, int(query_group[i]))
    j = int(0)
    k = starts[i]
    while wp.hash_grid_query_next(it, j):
        d = points[j] - q
        if wp.dot(d, d) < r2 and not (exclude_self != 0 and j == i):
            out_j[k] = wp.int64(j)
            k += wp.int64(1)


def grid_dim(num_points: int) -> int:
    """Hash-grid cells per axis for `num_points` points: ~8 cells per point, clamped to [8, 128]."""
    return int(min(_MAX_GRID_DIM, max(_MIN_GRID_DIM, round(2.0 * num_points ** (1.0 / 3.0)))))


def within_radius(query: Tensor, points: Tensor, qi: Tensor, pj: Tensor, radius: float) -> Tensor:
    """(P,) bool: pairs with ((points[pj] - query[qi])**2).sum(-1) < radius**2 on float32 query (N, 3) and
    points (M, 3) [m]: the exact test of every neighbour search here (`radius_pairs` and its cached reuse)."""
    return (points[pj] - query[qi]).square().sum(-1) < float(radius) ** 2


def _check_points(name: str, t: Tensor) -> None:
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"{name} must be (n, 3), got {tuple(t.shape)}")


def _check_batch(name: str, batch: Tensor | None, n: int, device: torch.device) -> Tensor:
    """Batch ids as (n,) int64 on `device`; all zeros when None."""
    if batch is None:
        return torch.zeros(n, dtype=torch.long, device=device)
    if batch.shape != (n,):
        raise ValueError(f"{name} must be ({n},), got {tuple(batch.shape)}")
    return batch.to(device=device, dtype=torch.long)


def _empty_pairs(device: torch.device) -> tuple[Tensor, Tensor]:
    e = torch.empty(0, dtype=torch.long, device=device)
    return e, e.clone()


@torch.no_grad()
def radius_pairs(
    query: Tensor,
    points: Tensor,
    radius: float,
    *,
    query_batch: Tensor | None = None,
    point_batch: Tensor | None = None,
    exclude_self: bool = False,
) -> tuple[Tensor, Tensor]:
    """All pairs (qi, pj) with ||points[pj] - query[qi]|| < radius (strict) and equal batch ids.

    query (N, 3), points (M, 3) [m]; radius [m]; batch ids (N,), (M,) int64 (default: one batch).
    exclude_self drops qi == pj (meaningful when query is points). Returns two (P,) int64 tensors on
    query's device, sorted by qi then pj. The distance test is `((points[pj] - query[qi])**2).sum(-1)
    < radius**2` evaluated in float32 torch, so a brute force written that way agrees exactly.
    Works on CPU and CUDA (warp hash grid, grouped by batch id, zero-copy from torch).
    """
    _check_points("query", query)
    _check_points("points", points)
    if not radius > 0.0:
        raise ValueError(f"radius must be positive, got {radius}")
    device = query.device
    if points.device != device:
        raise ValueError(f"query on {device} but points on {points.device}")
    n, m = query.shape[0], points.shape[0]
    query_batch = _check_batch("query_batch", query_batch, n, device)
    point_batch = _check_batch("point_batch", point_batch, m, device)
    if n == 0 or m == 0:
        return _empty_pairs(device)

    _init_warp()
    q32 = query.detach().to(torch.float32).contiguous()
    p32 = points.detach().to(torch.float32).contiguous()
    q_group = query_batch.to(torch.int32).contiguous()
    p_group = point_batch.to(torch.int32).contiguous()
    r_search = float(radius) * (1.0 + _CANDIDATE_SLACK)

    # Cell width = search radius, so a query visits 3x3x3 cells; dims only size the hash table (cells
    # hash modulo dims), so they come from the point count, not the extent: no host sync.
    dims = [grid_dim(m)] * 3

    wp_device = wp.device_from_torch(device)
    # Launch on torch's current stream so warp and torch work is ordered without extra syncs.
    stream = wp.stream_from_torch(torch.cuda.current_stream(device)) if device.type == "cuda" else None
    with wp.ScopedDevice(wp_device), (wp.ScopedStream(stream) if stream is not None else contextlib.nullcontext()):
        wq = wp.from_torch(q32, dtype=wp.vec3)
        wpts = wp.from_torch(p32, dtype=wp.vec3)
        wqg = wp.from_torch(q_group, dtype=wp.int32)
        wpg = wp.from_torch(p_group, dtype=wp.int32)
        grid = wp.HashGrid(*dims, device=wp_device)
        grid.build(wpts, r_search, groups=wpg)

        counts = torch.empty(n, dtype=torch.int32, device=device)
        wp.launch(
            _count_candidates,
            dim=n,
            inputs=[grid.id, wq, wqg, wpts, r_search, int(exclude_self)],
            outputs=[wp.from_torch(counts, dtype=wp.int32)],
            device=wp_device,
        )
        counts64 = counts.to(torch.long)
        ends = torch.cumsum(counts64, 0)
        total = int(ends[-1].item())
        if total == 0:
            return _empty_pairs(device)
        starts = (ends - counts64).contiguous()
        pj = torch.empty(total, dtype=torch.long, device=device)
        wp.launch(
            _fill_candidates,
            dim=n,
            inputs=[grid.id, wq, wqg, wpts, r_search, int(exclude_self), wp.from_torch(starts, dtype=wp.int64)],
            outputs=[wp.from_torch(pj, dtype=wp.int64)],
            device=wp_device,
        )
    qi = torch.repeat_interleave(torch.arange(n, device=device), counts64, output_size=total)

    # Exact test in torch (see _CANDIDATE_SLACK), then a deterministic order: the grid visits
    # cells in hash order and the group filter already holds.
    keep = within_radius(q32, p32, qi, pj, radius)
    qi, pj = qi[keep], pj[keep]
    order = torch.argsort(qi * m + pj)
    return qi[order], pj[order]


@torch.no_grad()
def nearest_index(
    query: Tensor,
    points: Tensor,
    query_batch: Tensor | None = None,
    point_batch: Tensor | None = None,
) -> Tensor:
    """Index (N,) int64 of the nearest point of the same batch for every query.

    query (N, 3), points (M, 3) [m]; batch ids (N,), (M,) int64 (default: one batch). Ties go to the
    lowest index. Raises ValueError if a query's batch has no points. Loops over batches and chunks
    of queries only (exact distances, no matmul expansion).
    """
    _check_points("query", query)
    _check_points("points", points)
    device = query.device
    n, m = query.shape[0], points.shape[0]
    query_batch = _check_batch("query_batch", query_batch, n, device)
    point_batch = _check_batch("point_batch", point_batch, m, device)
    out = torch.empty(n, dtype=torch.long, device=device)
    if n == 0:
        return out
    q = query.detach().to(torch.float32)
    p = points.detach().to(torch.float32)
    for b in torch.unique(query_batch).tolist():
        q_idx = torch.nonzero(query_batch == b).squeeze(1)
        p_idx = torch.nonzero(point_batch == b).squeeze(1)
        if p_idx.numel() == 0:
            raise ValueError(f"nearest_index: batch {b} has queries but no points")
        pb = p[p_idx]
        chunk = max(1, _CDIST_CHUNK_ELEMENTS // p_idx.numel())
        for s in range(0, q_idx.numel(), chunk):
            rows = q_idx[s : s + chunk]
            d = torch.cdist(q[rows], pb, compute_mode="donot_use_mm_for_euclid_dist")
            out[rows] = p_idx[d.argmin(dim=1)]
    return out
