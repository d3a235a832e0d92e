"""Verlet-skin neighbour reuse: the same pairs as fresh searches, rebuilt exactly when the skin bound fails."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tests.conftest import load_params
from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.layout import scene_layout
from wc.model.neighbor_cache import NeighborCache, PairQuery, exact_pairs
from wc.model.neighbors import grid_dim
from wc.model.rollout import rollout
from wc.model.worldcontact import WorldContact
from wc.train.data import episode_phases, read_phase_window


def _query(x: torch.Tensor, pts: torch.Tensor, radius: float, b: int, self_set: bool) -> PairQuery:
    n, m = x.shape[0] // b, pts.shape[0] // b
    qb, pb = torch.arange(b).repeat_interleave(n), torch.arange(b).repeat_interleave(m)
    return PairQuery(x, pts, radius, qb, pb, b, exclude_self=self_set)


def _assert_same(cache: NeighborCache, queries: dict[str, PairQuery]) -> None:
    got = cache.search(queries)
    for name, q in queries.items():
        ref = exact_pairs(q)
        assert torch.equal(got[name][0], ref[0]) and torch.equal(got[name][1], ref[1]), name


def test_cache_equals_fresh_search_while_points_move() -> None:
    g = torch.Generator().manual_seed(0)
    b, n, m, radius, skin = 2, 300, 80, 0.06, 0.02
    x = torch.rand(b * n, 3, generator=g) * 0.4
    s = torch.rand(b * m, 3, generator=g) * 0.4
    cache = NeighborCache(skin)
    for step in range(12):  # small random steps (some reuse), every 4th a large one (forces a rebuild)
        scale = 0.012 if step % 4 == 3 else 0.0015
        x = x + scale * torch.randn(x.shape, generator=g)
        s = s + scale * torch.randn(s.shape, generator=g)
        _assert_same(cache, {"self": _query(x, x, radius, b, True), "samples": _query(x, s, radius, b, False)})
    assert cache.reuses["self"] > 0 and cache.reuses["samples"] > 0
    assert cache.builds["self"] > 1 and cache.builds["samples"] > 1


def test_rebuild_exactly_when_a_point_moves_more_than_half_the_skin() -> None:
    g = torch.Generator().manual_seed(1)
    x = torch.rand(200, 3, generator=g) * 0.3
    cache = NeighborCache(0.01)
    q = lambda pts: {"self": _query(pts, pts, 0.05, 1, True)}  # noqa: E731
    cache.search(q(x))
    assert cache.builds == {"self": 1}
    shifted = x + torch.tensor([0.05, -0.03, 0.02])  # a common translation moves no pair
    _assert_same(cache, q(shifted))
    assert cache.builds == {"self": 1} and cache.reuses == {"self": 1}
    small = shifted.clone()
    small[7] += torch.tensor([0.0024, 0.0, 0.0])  # relative move 2.4 mm: bound ~ 2 x 2.4 < 10 mm skin
    _assert_same(cache, q(small))
    assert cache.builds == {"self": 1}
    big = shifted.clone()
    big[7] += torch.tensor([0.0, 0.0052, 0.0])  # beyond skin / 2 relative to the rest: must rebuild
    _assert_same(cache, q(big))
    assert cache.builds == {"self": 2}


def test_shape_or_batch_change_replaces_the_entry() -> None:
    g = torch.Generator().manual_seed(2)
    x = torch.rand(2 * 100, 3, generator=g) * 0.3
    cache = NeighborCache(0.01)
    _assert_same(cache, {"self": _query(x, x, 0.05, 2, True)})
    _assert_same(cache, {"self": _query(x, x, 0.05, 1, True)})  # same points, one scene: new pairs
    _assert_same(cache, {"self": _query(x[:100], x[:100], 0.05, 1, True)})
    assert cache.builds["self"] == 3
    with pytest.raises(ValueError, match="skin"):
        NeighborCache(0.0)


def test_grid_dim_needs_no_extent() -> None:
    assert grid_dim(1) == 8 and grid_dim(20_000) == 54 and grid_dim(10**9) == 128


@pytest.fixture(scope="module")
def case(synthetic_store):
    params = load_params()
    path = synthetic_store(params, [("fall", "test")], frames=9)
    store = TrajectoryStore(path)
    phase = episode_phases(store, store.episode_ids[0])[0]
    cfg = replace(load_section(params, "model", ModelConfig), encoder_levels=1, decoder_layers=1)
    a = {k: torch.from_numpy(v)[None] for k, v in read_phase_window(store, phase, 0, 9).items()}
    layout = scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), cfg.tag_scale)
    torch.manual_seed(0)
    # delta scales of cm per step: the rollout deforms the bag, so the cache both reuses and rebuilds
    model = WorldContact(cfg, velocity_m_s=0.3, delta_x_m=0.3, delta_v_m_s=0.3).eval()
    return model, layout, a, store.dt


def test_rollout_with_reuse_equals_reference(case) -> None:
    model, layout, a, dt = case
    with torch.no_grad():
        x_ref, v_ref = rollout(model, layout, a["x"][:, 0], a["v"][:, 0], a["poses"], dt, neighbor_skin_m=0.0)
        moved = (x_ref[:, 1:] - x_ref[:, :-1]).norm(dim=-1).amax()
        assert moved > 1e-3  # the test means something only if points move between steps
        for skin in (0.004, 0.5):  # rebuilds happen / never needed after the first search
            cache = model.neighbor_cache(layout, skin)
            x, v = rollout(model, layout, a["x"][:, 0], a["v"][:, 0], a["poses"], dt, neighbor_skin_m=skin)
            assert torch.equal(x, x_ref) and torch.equal(v, v_ref)
            assert cache.reuses.get("spatial", 0) > 0
            if skin == 0.5:
                assert cache.builds["spatial"] == 1
            else:
                assert cache.builds["spatial"] > 1
        # a second batch shape on the same layout (the cache lives on it) stays exact
        x2, _ = rollout(model, layout, a["x"][:, 0].expand(2, -1, -1), a["v"][:, 0].expand(2, -1, -1),
                        a["poses"].expand(2, -1, -1, -1), dt, neighbor_skin_m=0.004)
        assert torch.equal(x2[0], x_ref[0]) and torch.equal(x2[1], x_ref[0])


def test_non_finite_state_is_refused_before_any_search(case) -> None:
    model, layout, a, dt = case
    x0 = a["x"][:, 0].clone()
    x0[0, 3, 1] = float("nan")
    with torch.no_grad(), pytest.raises(ValueError, match="non-finite x"):
        rollout(model, layout, x0, a["v"][:, 0], a["poses"], dt, neighbor_skin_m=0.01)


def test_config_rejects_negative_skin() -> None:
    params = load_params()
    with pytest.raises(ValueError, match="neighbor_skin_m"):
        ModelConfig(**{**params["model"], "neighbor_skin_m": -0.001}).validate()
