"""Verlet-skin reuse of fixed-radius neighbour pairs across rollout steps.

A neighbour set is searched once with radius + skin; the candidate pairs are kept with the positions
they were searched at. On a later step the candidates are reused while no pair can have entered the
radius from outside radius + skin: with per-scene displacements since the build, taken relative to a
common shift c_b (the scene's mean query displacement, so a shared translation does not count),
max |Δq - c_b| + max |Δp - c_b| < skin. Each reuse then keeps exactly the candidates with
`sum((p_j - q_i)^2) < radius^2` in float32, the test `radius_pairs` applies, in the same (qi, pj)
order: the pairs equal a fresh search bit for bit. Nothing here depends on the objects or the scene.

All per-set checks of a step and any flags the caller adds are read back in one host sync; a reuse
needs no other sync (`torch.nonzero_static` with the count read in that sync).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from wc.model.neighbors import radius_pairs, within_radius

_SKIN_MARGIN = 1.0e-3  # reuse only while the displacement bound is below skin * (1 - margin): rounding guard


@dataclass(frozen=True)
class PairQuery:
    """One neighbour set to search: pairs (qi, pj) with |points[pj] - query[qi]| < radius, equal batch ids.

    query (N, 3), points (M, 3) float32 [m]; batch ids (N,), (M,) int64 in [0, scenes).
    """

    query: Tensor
    points: Tensor
    radius: float
    query_batch: Tensor
    point_batch: Tensor
    scenes: int
    exclude_self: bool = False


@dataclass
class _Entry:
    """Candidates of one set, with what they were searched at."""

    signature: tuple
    query_batch: Tensor  # (N,)
    point_batch: Tensor  # (M,)
    query_ref: Tensor  # (N, 3) positions at the build
    points_ref: Tensor  # (M, 3)
    qi: Tensor  # (P_cand,) candidate pairs within radius + skin, sorted by qi then pj
    pj: Tensor


def exact_pairs(q: PairQuery) -> tuple[Tensor, Tensor]:
    """The reference: a fresh `radius_pairs` search."""
    return radius_pairs(q.query, q.points, q.radius, query_batch=q.query_batch, point_batch=q.point_batch,
                        exclude_self=q.exclude_self)


def _within(q: PairQuery, qi: Tensor, pj: Tensor) -> Tensor:
    """(P,) bool: the candidates within q.radius, the same float32 expression as `radius_pairs`'s filter."""
    return within_radius(q.query.detach().to(torch.float32), q.points.detach().to(torch.float32), qi, pj, q.radius)


def _max_deviation(d: Tensor, batch: Tensor, shift: Tensor, scenes: int) -> Tensor:
    """(scenes,) max over each scene's rows of |d - shift[batch]|; 0 for a scene without rows."""
    dev = (d - shift[batch]).norm(dim=-1)
    return torch.zeros(scenes, dtype=d.dtype, device=d.device).scatter_reduce(0, batch, dev, "amax")


@dataclass
class NeighborCache:
    """Candidate pairs per named neighbour set, reused while the Verlet-skin bound holds.

    skin_m > 0 [m]. Valid for any input (the bound is checked against the positions of the build), so it
    may outlive one rollout; an entry is replaced when the set's shapes, radius or device change.
    `builds` / `reuses` count per set name.
    """

    skin_m: float
    entries: dict[str, _Entry] = field(default_factory=dict, repr=False)
    builds: dict[str, int] = field(default_factory=dict)
    reuses: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.skin_m > 0.0:
            raise ValueError(f"neighbour skin must be > 0 m (0 means no cache), got {self.skin_m}")

    @staticmethod
    def _signature(q: PairQuery) -> tuple:
        return (q.query.shape[0], q.points.shape[0], float(q.radius), q.exclude_self, q.scenes, q.query.device)

    def _status(self, e: _Entry, q: PairQuery) -> tuple[Tensor, Tensor]:
        """[reusable, number of candidates within the radius] (2,) int64 on device, and that mask (P_cand,)."""
        qx = q.query.detach().to(torch.float32)
        px = q.points.detach().to(torch.float32)
        dq, dp = qx - e.query_ref, px - e.points_ref
        rows = torch.zeros(q.scenes, dtype=torch.float32, device=qx.device).index_add_(
            0, q.query_batch, torch.ones_like(dq[:, 0]))
        shift = torch.zeros(q.scenes, 3, dtype=torch.float32, device=qx.device).index_add_(0, q.query_batch, dq)
        shift = shift / rows.clamp_min(1.0)[:, None]  # the scene's mean query displacement
        bound = (_max_deviation(dq, q.query_batch, shift, q.scenes)
                 + _max_deviation(dp, q.point_batch, shift, q.scenes))  # (scenes,) [m]
        same = (e.query_batch == q.query_batch).all() & (e.point_batch == q.point_batch).all()
        ok = (bound < self.skin_m * (1.0 - _SKIN_MARGIN)).all() & same
        mask = _within(q, e.qi, e.pj)
        return torch.stack((ok.long(), mask.sum())), mask

    def _build(self, name: str, q: PairQuery) -> tuple[Tensor, Tensor]:
        qi, pj = radius_pairs(q.query, q.points, q.radius + self.skin_m, query_batch=q.query_batch,
                              point_batch=q.point_batch, exclude_self=q.exclude_self)
        self.entries[name] = _Entry(self._signature(q), q.query_batch.clone(), q.point_batch.clone(),
                                    q.query.detach().to(torch.float32).clone(),
                                    q.points.detach().to(torch.float32).clone(), qi, pj)
        self.builds[name] = self.builds.get(name, 0) + 1
        keep = _within(q, qi, pj)
        return qi[keep], pj[keep]

    def search(self, queries: dict[str, PairQuery], read_back: Tensor | None = None,
               check: Callable[[list[int]], None] | None = None) -> dict[str, tuple[Tensor, Tensor]]:
        """Pairs (qi, pj) per named set, equal to `exact_pairs`.

        read_back: a small integer device tensor the caller needs on the host (e.g. validity flags of the
        state); it is read in the same single host sync as the reuse checks and handed, as a list, to
        `check`, which runs before any search (so it can refuse a non-finite state first).
        """
        pending = {name: self.entries[name] for name, q in queries.items()
                   if name in self.entries and self.entries[name].signature == self._signature(q)
                   and q.query.shape[0] > 0 and q.points.shape[0] > 0}
        status = {name: self._status(e, queries[name]) for name, e in pending.items()}
        parts = [s for s, _ in status.values()] + ([read_back.reshape(-1).long()] if read_back is not None else [])
        host = torch.cat(parts).tolist() if parts else []  # the one host sync of a step
        if check is not None:
            check(host[2 * len(pending):])
        out: dict[str, tuple[Tensor, Tensor]] = {}
        for k, (name, e) in enumerate(pending.items()):
            reusable, count = host[2 * k], host[2 * k + 1]
            if reusable:
                idx = torch.nonzero_static(status[name][1], size=count).squeeze(1)
                out[name] = (e.qi[idx], e.pj[idx])
                self.reuses[name] = self.reuses.get(name, 0) + 1
        for name, q in queries.items():
            if name in out:
                continue
            if q.query.shape[0] == 0 or q.points.shape[0] == 0:
                out[name] = exact_pairs(q)
            else:
                out[name] = self._build(name, q)
        return {name: out[name] for name in queries}


def search_pairs(queries: dict[str, PairQuery], cache: NeighborCache | None = None, read_back: Tensor | None = None,
                 check: Callable[[list[int]], None] | None = None) -> dict[str, tuple[Tensor, Tensor]]:
    """Pairs per named set through `cache`, or fresh `radius_pairs` searches (the reference) when it is None;
    `read_back` / `check` as `NeighborCache.search`."""
    if cache is not None:
        return cache.search(queries, read_back, check)
    if check is not None:
        check(read_back.reshape(-1).long().tolist() if read_back is not None else [])
    return {name: exact_pairs(q) for name, q in queries.items()}
