"""Static-shape neighbour search: the same (qi, pj) as `radius_pairs` while nothing overflows, overflow counted
when a capacity is short, shapes independent of the data, and no graph break under torch.compile(fullgraph=True)."""

from __future__ import annotations

import pytest
import torch

import wc.model.padded_neighbors as pn
from wc.model.neighbors import radius_pairs
from wc.model.padded_neighbors import (NeighborCapacity, PaddedNeighbors, capacity_for, grid_cells, neighbor_counts,
                                       padded_radius_neighbors)


def _batch(scenes: int, per_scene: int) -> torch.Tensor:
    return torch.arange(scenes).repeat_interleave(per_scene)


def _cloud(kind: str, count: int, g: torch.Generator) -> torch.Tensor:
    """(count, 3) [m]: uniform in a 0.5 m cube, or clustered (tight blobs around 4 centres: dense cells)."""
    if kind == "uniform":
        return torch.rand(count, 3, generator=g) * 0.5
    centres = torch.rand(4, 3, generator=g) * 0.5
    return centres[torch.randint(0, 4, (count,), generator=g)] + 0.01 * torch.randn(count, 3, generator=g)


def _flatten(found: PaddedNeighbors) -> tuple[torch.Tensor, torch.Tensor]:
    """Valid slots in row order as (qi, pj)."""
    rows = torch.arange(found.index.shape[0])[:, None].expand_as(found.index)
    return rows[found.valid], found.index[found.valid]


def _search(q, p, radius, capacity, qb, pb, scenes, exclude_self=False) -> PaddedNeighbors:
    return padded_radius_neighbors(q, p, radius, capacity, query_batch=qb, point_batch=pb, scenes=scenes,
                                   exclude_self=exclude_self)


def _assert_matches_reference(q, p, radius, qb, pb, scenes, exclude_self) -> PaddedNeighbors:
    """Search with capacities sized from the data and compare with `radius_pairs`; returns the search."""
    k, c = neighbor_counts(q, p, radius, query_batch=qb, point_batch=pb, scenes=scenes, exclude_self=exclude_self)
    found = _search(q, p, radius, capacity_for(k, c, 1.0), qb, pb, scenes, exclude_self)
    qi, pj = radius_pairs(q, p, radius, query_batch=qb, point_batch=pb, exclude_self=exclude_self)
    assert qi.numel() > 0
    assert int(found.overflow) == 0
    got_qi, got_pj = _flatten(found)
    assert torch.equal(got_qi, qi) and torch.equal(got_pj, pj)
    count = found.valid.sum(1, keepdim=True)  # valid slots packed at the start of each row
    assert torch.equal(found.valid, torch.arange(found.valid.shape[1]) < count)
    assert int(found.index.min()) >= 0 and int(found.index.max()) < p.shape[0]
    assert int(torch.bincount(qi, minlength=q.shape[0]).max()) == k
    return found


@pytest.mark.parametrize("kind", ["uniform", "clustered"])
@pytest.mark.parametrize("exclude_self", [False, True])
def test_equals_radius_pairs_on_points_themselves(kind: str, exclude_self: bool) -> None:
    g = torch.Generator().manual_seed(0)
    scenes, n = 3, 400
    x = _cloud(kind, scenes * n, g)
    b = _batch(scenes, n)
    _assert_matches_reference(x, x, 0.05, b, b, scenes, exclude_self)


@pytest.mark.parametrize("kind", ["uniform", "clustered"])
def test_equals_radius_pairs_for_other_points(kind: str) -> None:
    g = torch.Generator().manual_seed(1)
    scenes, n, m = 2, 500, 300
    q, p = _cloud(kind, scenes * (n + m), g).split([scenes * n, scenes * m])  # the same clusters
    qb, pb = _batch(scenes, n), _batch(scenes, m)
    _assert_matches_reference(q, p, 0.06, qb, pb, scenes, False)
    _assert_matches_reference(q.double(), p.double(), 0.06, qb, pb, scenes, False)  # float32 geometry either way


def test_equals_radius_pairs_on_a_lattice_at_the_radius() -> None:
    """Distances equal to the radius (strict test) and a hair below it, across cell boundaries."""
    r = 0.05
    axis = torch.arange(8, dtype=torch.float32)
    lattice = torch.cartesian_prod(axis, axis, axis)
    for spacing in (r, r * (1 - 2.0 ** -23), r * (1 + 2.0 ** -23)):
        x = lattice * spacing - 0.1
        b = torch.zeros(x.shape[0], dtype=torch.long)
        _assert_matches_reference(x, x, r, b, b, 1, True)


def test_chunked_search_equals_one_chunk(monkeypatch: pytest.MonkeyPatch) -> None:
    g = torch.Generator().manual_seed(2)
    x = _cloud("uniform", 600, g)
    b = _batch(2, 300)
    cap = NeighborCapacity(16, 16)
    whole = _search(x, x, 0.05, cap, b, b, 2, True)
    monkeypatch.setattr(pn, "_CHUNK_CANDIDATES", 27 * 16 * 37)  # 37 queries per chunk: 17 chunks, last one short
    chunked = _search(x, x, 0.05, cap, b, b, 2, True)
    assert torch.equal(whole.index, chunked.index) and torch.equal(whole.valid, chunked.valid)
    assert int(whole.overflow) == int(chunked.overflow)


def test_overflow_counts_queries_beyond_k() -> None:
    g = torch.Generator().manual_seed(3)
    x = _cloud("clustered", 800, g)
    b = _batch(2, 400)
    k, c = neighbor_counts(x, x, 0.04, query_batch=b, point_batch=b, scenes=2, exclude_self=True)
    qi, _ = radius_pairs(x, x, 0.04, query_batch=b, point_batch=b, exclude_self=True)
    per_query = torch.bincount(qi, minlength=x.shape[0])
    short = _search(x, x, 0.04, NeighborCapacity(k - 1, c), b, b, 2, True)
    assert int(short.overflow) == int((per_query > k - 1).sum()) > 0
    assert int(_search(x, x, 0.04, NeighborCapacity(k, c), b, b, 2, True).overflow) == 0


def test_overflow_counts_cells_beyond_c() -> None:
    g = torch.Generator().manual_seed(4)
    x = _cloud("clustered", 800, g)
    b = _batch(2, 400)
    k, c = neighbor_counts(x, x, 0.04, query_batch=b, point_batch=b, scenes=2)
    assert c > 1
    assert int(_search(x, x, 0.04, NeighborCapacity(k, c - 1), b, b, 2).overflow) > 0
    assert int(_search(x, x, 0.04, NeighborCapacity(k, c), b, b, 2).overflow) == 0


def test_far_points_still_find_their_neighbours() -> None:
    """Beyond +-2^15 cells the coordinates clamp: far points share edge cells but keep their neighbours."""
    g = torch.Generator().manual_seed(5)
    r = 0.05
    near = torch.rand(300, 3, generator=g) * 0.3
    far = torch.tensor([5000.0, 0.1, -0.2]) + torch.rand(300, 3, generator=g) * 0.3
    very_far = torch.tensor([-0.3, -5000.0, 7000.0]) + torch.rand(300, 3, generator=g) * 0.3
    x = torch.cat((near, far, very_far))
    cells = grid_cells(x, r)
    assert (cells[300:600, 0] == 2**16 - 1).all()  # clamped at the top edge
    assert (cells[600:, 1] == 0).all() and (cells[600:, 2] == 2**16 - 1).all()
    b = torch.zeros(x.shape[0], dtype=torch.long)
    found = _assert_matches_reference(x, x, r, b, b, 1, True)
    assert found.valid[300:600].any(1).float().mean() > 0.5 and found.valid[600:].any(1).float().mean() > 0.5


def test_output_shapes_do_not_depend_on_the_data() -> None:
    g = torch.Generator().manual_seed(6)
    cap = NeighborCapacity(24, 16)
    b = _batch(2, 250)
    sparse = torch.rand(500, 3, generator=g) * 2.0
    dense = torch.rand(500, 3, generator=g) * 0.05
    out = [_search(x, x, 0.05, cap, b, b, 2, True) for x in (sparse, dense)]
    assert int(out[0].valid.sum()) != int(out[1].valid.sum())  # really different densities
    assert int(out[1].overflow) > 0
    for o in out:
        assert o.index.shape == o.valid.shape == (500, 24) and o.overflow.shape == ()
        assert o.index.dtype == torch.long and o.valid.dtype == torch.bool and o.overflow.dtype == torch.long


def test_compiles_with_fullgraph_and_matches_eager() -> None:
    """fullgraph=True raises on a graph break: any host sync or data-dependent shape in the search."""
    g = torch.Generator().manual_seed(7)
    q, p = _cloud("uniform", 400, g), _cloud("clustered", 300, g)
    qb, pb = _batch(2, 200), _batch(2, 150)
    cap = NeighborCapacity(32, 24)

    def search(q, p, qb, pb):
        found = padded_radius_neighbors(q, p, 0.06, cap, query_batch=qb, point_batch=pb, scenes=2)
        return found.index, found.valid, found.overflow

    torch._dynamo.reset()
    compiled = torch.compile(search, fullgraph=True, backend="eager")
    want, got = search(q, p, qb, pb), compiled(q, p, qb, pb)
    assert int(want[1].sum()) > 0
    for w, o in zip(want, got):
        assert torch.equal(w, o)


@pytest.mark.parametrize("change, match", [
    ({"query": torch.zeros(10, 2)}, "query"),
    ({"points": torch.zeros(8)}, "points"),
    ({"radius": 0.0}, "radius"),
    ({"radius": -0.1}, "radius"),
    ({"radius": float("nan")}, "radius"),
    ({"query_batch": torch.zeros(9, dtype=torch.long)}, "query_batch"),
    ({"point_batch": torch.zeros(8, 1, dtype=torch.long)}, "point_batch"),
    ({"point_batch": torch.zeros(8)}, "point_batch"),
    ({"scenes": 0}, "scenes"),
    ({"scenes": 2**15 + 1}, "scenes"),
    ({"capacity": (8, 8)}, "capacity"),
])
def test_bad_input_names_the_argument(change: dict, match: str) -> None:
    args = {"query": torch.zeros(10, 3), "points": torch.zeros(8, 3), "radius": 0.1,
            "capacity": NeighborCapacity(8, 8), "query_batch": torch.zeros(10, dtype=torch.long),
            "point_batch": torch.zeros(8, dtype=torch.long), "scenes": 1} | change
    with pytest.raises(ValueError, match=match):
        padded_radius_neighbors(args["query"], args["points"], args["radius"], args["capacity"],
                                query_batch=args["query_batch"], point_batch=args["point_batch"], scenes=args["scenes"])


def test_bad_capacities_name_the_argument() -> None:
    with pytest.raises(ValueError, match="max_neighbors"):
        NeighborCapacity(0, 8)
    with pytest.raises(ValueError, match="cell_capacity"):
        NeighborCapacity(8, 0)
    with pytest.raises(ValueError, match="headroom"):
        capacity_for(10, 10, 0.9)


def test_capacity_for_rounds_up_with_headroom() -> None:
    assert capacity_for(0, 1, 1.0) == NeighborCapacity(8, 8)
    assert capacity_for(8, 9, 1.0) == NeighborCapacity(8, 16)
    assert capacity_for(30, 12, 1.5) == NeighborCapacity(48, 24)


@pytest.mark.parametrize("n, m", [(0, 5), (5, 0), (0, 0)])
def test_empty_inputs(n: int, m: int) -> None:
    q, p = torch.rand(n, 3), torch.rand(m, 3)
    qb, pb = torch.zeros(n, dtype=torch.long), torch.zeros(m, dtype=torch.long)
    found = _search(q, p, 0.1, NeighborCapacity(8, 8), qb, pb, 1)
    assert found.index.shape == found.valid.shape == (n, 8)
    assert not found.valid.any() and int(found.overflow) == 0
    assert neighbor_counts(q, p, 0.1, query_batch=qb, point_batch=pb, scenes=1) == (0, 0)
