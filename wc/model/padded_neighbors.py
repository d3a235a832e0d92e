"""Fixed-radius neighbours with a static shape: K padded slots per query from a sorted cell grid, in pure torch.

The fast-path replacement of `radius_pairs`: output shapes depend only on (N, M, K, C) and nothing syncs with the
host, so a step using it compiles with `torch.compile(fullgraph=True)` and captures as a CUDA graph. The selection
is the same float32 test (`within_radius`) in the same (qi, pj) order, so while `overflow` is 0 the valid slots
flattened row by row equal `radius_pairs` bit for bit. Nothing is dropped silently: a query with more than K
neighbours, or a visited cell with more than C points, counts in `overflow` (the caller raises or grows K, C).

Positions are float32 [m]; batch ids are int64 scene indices in [0, scenes). No gradient flows through the search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from wc.model.neighbors import _check_batch, _check_points, radius_pairs, within_radius

_CELL_BITS = 16  # bits per cell coordinate in a key; the scene id takes the top bits
_CELL_MAX = (1 << _CELL_BITS) - 1
_CELL_OFFSET = 1 << (_CELL_BITS - 1)  # cell 0 of space sits at coordinate 2^15: +-2^15 cells around the origin
MAX_SCENES = 1 << 15  # scene * 2^48 + cells stays below 2^63
# Cells are a hair wider than the radius and cell coordinates are taken in float64, so a pair that passes the
# float32 test (whose rounding can admit a true distance a few ulps above the radius) never lies two cells apart.
_CELL_SLACK = 1.0e-5
_CHUNK_CANDIDATES = 1 << 23  # (query, candidate) slots handled at once; bounds the memory of one chunk
_CAPACITY_QUANTUM = 8


@dataclass(frozen=True)
class NeighborCapacity:
    """Static capacities of one search: K slots per query, at most C points read from one grid cell."""

    max_neighbors: int  # K
    cell_capacity: int  # C

    def __post_init__(self) -> None:
        for name in ("max_neighbors", "cell_capacity"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")


@dataclass
class PaddedNeighbors:
    """Neighbours of N queries in K slots: row i holds i's neighbours in ascending index order, then padding.

    index (N, K) int64 into points (padding slots hold 0); valid (N, K) bool; overflow () int64: queries with
    more than K neighbours plus (query, cell) visits of cells with more than C points (0: nothing dropped).
    """

    index: Tensor
    valid: Tensor
    overflow: Tensor


def _cell_width(radius: float) -> float:
    return float(radius) * (1.0 + _CELL_SLACK)


def grid_cells(x: Tensor, radius: float) -> Tensor:
    """(n, 3) int64 cell coordinates of positions x (n, 3) [m]: floor(x / width) + 2^15 clamped to [0, 2^16 - 1].

    Clamping is monotone, so points within one cell width stay within +-1 cell; far points share edge cells.
    """
    c = torch.floor(x.detach().to(torch.float64) / _cell_width(radius)) + _CELL_OFFSET
    c = torch.nan_to_num(c, nan=0.0)  # a NaN position passes no distance test; any cell will do
    return c.clamp(0, _CELL_MAX).to(torch.long)


def cell_keys(cells: Tensor, batch: Tensor) -> Tensor:
    """int64 keys ((scene * 2^16 + cx) * 2^16 + cy) * 2^16 + cz of cells (..., 3) with scene ids batch (...)."""
    key = batch
    for axis in range(3):
        key = (key << _CELL_BITS) + cells[..., axis]
    return key


def _neighbor_offsets(device: torch.device) -> Tensor:
    """(27, 3) int64 cell offsets in {-1, 0, 1}^3."""
    r = torch.arange(-1, 2, device=device)
    return torch.cartesian_prod(r, r, r)


@dataclass
class _SortedGrid:
    """Points sorted by cell key: keys (M,) ascending, order (M,) original index of each sorted point."""

    keys: Tensor
    order: Tensor


def _sorted_grid(points: Tensor, point_batch: Tensor, radius: float) -> _SortedGrid:
    keys, order = torch.sort(cell_keys(grid_cells(points, radius), point_batch), stable=True)
    return _SortedGrid(keys, order)


def _cell_ranges(grid: _SortedGrid, cells: Tensor, batch: Tensor) -> tuple[Tensor, Tensor]:
    """[start, end) (n, 27) in the sorted points of the 27 cells around cells (n, 3); offsets leaving the grid
    get an empty range (no cell is visited twice)."""
    around = cells[:, None, :] + _neighbor_offsets(cells.device)  # (n, 27, 3)
    inside = ((around >= 0) & (around <= _CELL_MAX)).all(-1)
    keys = torch.where(inside, cell_keys(around, batch[:, None].expand_as(inside)), -1)  # -1: no point's key
    return (torch.searchsorted(grid.keys, keys, side="left"), torch.searchsorted(grid.keys, keys, side="right"))


def _select_sorted(j: Tensor, keep: Tensor, m: int, k: int) -> tuple[Tensor, Tensor]:
    """The k smallest kept candidates j (n, L) per row, ascending, as (index (n, k), valid (n, k)); sentinel m."""
    key = torch.where(keep, j, m)
    if key.shape[1] < k:
        key = torch.cat((key, key.new_full((key.shape[0], k - key.shape[1]), m)), dim=1)
    first = torch.topk(key, k, dim=1, largest=False, sorted=True).values
    valid = first < m
    return torch.where(valid, first, 0), valid


def _search_chunk(q32: Tensor, p32: Tensor, grid: _SortedGrid, cells: Tensor, batch: Tensor, first: int,
                  radius: float, capacity: NeighborCapacity, exclude_self: bool) -> PaddedNeighbors:
    """Padded neighbours of queries first .. first + n - 1 (cells (n, 3), batch (n,))."""
    n, m, c = cells.shape[0], p32.shape[0], capacity.cell_capacity
    start, end = _cell_ranges(grid, cells, batch)  # (n, 27)
    cell_overflow = (end - start > c).sum()
    slot = start[..., None] + torch.arange(c, device=start.device)  # (n, 27, C) positions in the sorted points
    in_cell = (slot < end[..., None]).reshape(n, -1)
    j = grid.order[slot.clamp(max=m - 1)].reshape(n, -1)  # (n, 27 C) candidate point indices
    qi = torch.arange(first, first + n, device=j.device)[:, None].expand_as(j)
    keep = in_cell & within_radius(q32, p32, qi.reshape(-1), j.reshape(-1), radius).reshape(n, -1)
    if exclude_self:
        keep = keep & (j != qi)
    index, valid = _select_sorted(j, keep, m, capacity.max_neighbors)
    query_overflow = (keep.sum(1) > capacity.max_neighbors).sum()
    return PaddedNeighbors(index, valid, query_overflow + cell_overflow)


def _check_search(query: Tensor, points: Tensor, radius: float, capacity: NeighborCapacity, query_batch: Tensor,
                  point_batch: Tensor, scenes: int) -> tuple[Tensor, Tensor]:
    """Validate the arguments (host-side shapes and numbers only); batch ids as int64 on query's device."""
    _check_points("query", query)
    _check_points("points", points)
    if points.device != query.device:
        raise ValueError(f"query on {query.device} but points on {points.device}")
    if not (isinstance(radius, (int, float)) and math.isfinite(radius) and radius > 0.0):
        raise ValueError(f"radius must be a positive finite number [m], got {radius!r}")
    if not isinstance(capacity, NeighborCapacity):
        raise ValueError(f"capacity must be a NeighborCapacity, got {type(capacity).__name__}")
    if not (isinstance(scenes, int) and 1 <= scenes <= MAX_SCENES):
        raise ValueError(f"scenes must be an int in [1, {MAX_SCENES}], got {scenes!r}")
    for name, batch in (("query_batch", query_batch), ("point_batch", point_batch)):
        if not isinstance(batch, Tensor) or batch.is_floating_point() or batch.is_complex():
            raise ValueError(f"{name} must be an integer tensor of scene ids")
    return (_check_batch("query_batch", query_batch, query.shape[0], query.device),
            _check_batch("point_batch", point_batch, points.shape[0], query.device))


def padded_radius_neighbors(query: Tensor, points: Tensor, radius: float, capacity: NeighborCapacity, *,
                            query_batch: Tensor, point_batch: Tensor, scenes: int,
                            exclude_self: bool = False) -> PaddedNeighbors:
    """Neighbours j of every query i with `within_radius` true, equal scene ids (and j != i if exclude_self).

    query (N, 3), points (M, 3) [m]; radius [m]; batch ids (N,), (M,) int64 in [0, scenes). Returns index / valid
    (N, K) with row i's neighbours in ascending j at slots [0, count_i), overflow () int64 (see PaddedNeighbors).
    Shapes depend only on (N, M, K, C); no host sync, so it traces with torch.compile(fullgraph=True).
    """
    query_batch, point_batch = _check_search(query, points, radius, capacity, query_batch, point_batch, scenes)
    n, m, k, device = query.shape[0], points.shape[0], capacity.max_neighbors, query.device
    if n == 0 or m == 0:
        return PaddedNeighbors(torch.zeros(n, k, dtype=torch.long, device=device),
                               torch.zeros(n, k, dtype=torch.bool, device=device),
                               torch.zeros((), dtype=torch.long, device=device))
    q32 = query.detach().to(torch.float32)
    p32 = points.detach().to(torch.float32)
    grid = _sorted_grid(p32, point_batch, radius)
    cells = grid_cells(q32, radius)
    rows = max(1, _CHUNK_CANDIDATES // (27 * capacity.cell_capacity))
    if n <= rows:  # one chunk: a bound on n, not its value, so a compiled search stays valid for any n below it
        return _search_chunk(q32, p32, grid, cells, query_batch, 0, radius, capacity, exclude_self)
    parts = [_search_chunk(q32, p32, grid, cells[s:s + rows], query_batch[s:s + rows], s, radius, capacity,
                           exclude_self) for s in range(0, n, rows)]
    return PaddedNeighbors(torch.cat([p.index for p in parts]), torch.cat([p.valid for p in parts]),
                           torch.stack([p.overflow for p in parts]).sum())


@torch.no_grad()
def neighbor_counts(query: Tensor, points: Tensor, radius: float, *, query_batch: Tensor, point_batch: Tensor,
                    scenes: int, exclude_self: bool = False) -> tuple[int, int]:
    """(most neighbours of any query, most points in any grid cell) — exact, may sync (used once, before training).

    Arguments as `padded_radius_neighbors`; (0, 0) for empty inputs. The cells are the search's own grid.
    """
    query_batch, point_batch = _check_search(query, points, radius, NeighborCapacity(1, 1), query_batch,
                                             point_batch, scenes)
    if query.shape[0] == 0 or points.shape[0] == 0:
        return 0, 0
    qi, _ = radius_pairs(query, points, radius, query_batch=query_batch, point_batch=point_batch,
                         exclude_self=exclude_self)
    most_neighbors = int(torch.bincount(qi, minlength=query.shape[0]).max()) if qi.numel() else 0
    keys = cell_keys(grid_cells(points.detach().to(torch.float32), radius), point_batch)
    most_in_cell = int(torch.unique(keys, return_counts=True)[1].max())
    return most_neighbors, most_in_cell


def capacity_for(max_neighbors: int, max_cell: int, headroom: float) -> NeighborCapacity:
    """Capacities with headroom (>= 1), rounded up to a multiple of 8, at least 8."""
    if not headroom >= 1.0:
        raise ValueError(f"headroom must be >= 1, got {headroom!r}")
    for name, value in (("max_neighbors", max_neighbors), ("max_cell", max_cell)):
        if value < 0:
            raise ValueError(f"{name} must be >= 0, got {value!r}")

    def rounded(count: int) -> int:
        q = _CAPACITY_QUANTUM
        return max(q, math.ceil(math.ceil(count * headroom) / q) * q)

    return NeighborCapacity(rounded(int(max_neighbors)), rounded(int(max_cell)))
