"""Static-shape neighbour sets of one scene layout: the fast path of the tokenizer (training and rollouts).

Each searched set (spatial, environment, controllable) gets K padded slots per vertex from a sorted cell grid
in torch (`wc.model.padded_neighbors`), and the static topology pairs are padded once per layout, so a
model step has shapes fixed by (B, N, M) and the capacities alone: no host synchronisation, compilable and
capturable as a CUDA graph. Neighbours are never dropped silently: every search adds the queries it could
not hold to `overflow` (per set, on the device); the caller reads it at its next sync and raises, or grows the
capacities (`grown`) and repeats the step.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from wc.model.neighbor_cache import PairQuery
from wc.model.padded_neighbors import NeighborCapacity, PaddedNeighbors, capacity_for, padded_radius_neighbors

SEARCHED_SETS = ("spatial", "environment", "controllable")


def padded_pairs(ti: Tensor, tj: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Pairs (ti, tj) (P,) sorted by ti as (index (n, K), valid (n, K)): row i holds i's tj in order, K = most pairs
    of any i (at least 1); padding slots point at 0. Built once per layout (it syncs)."""
    counts = torch.bincount(ti, minlength=n)
    k = max(1, int(counts.max()) if ti.numel() else 1)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(ti.numel(), device=ti.device) - first[ti]
    index = torch.zeros(n, k, dtype=torch.long, device=ti.device)
    valid = torch.zeros(n, k, dtype=torch.bool, device=ti.device)
    index[ti, slot] = tj
    valid[ti, slot] = True
    return index, valid


@dataclass
class FixedNeighbors:
    """The layout's static-shape neighbour search: capacities per searched set, padded topology, overflow counter.

    topology_index / topology_valid (N, Kt): one scene's rest-(u, v) neighbours (offset per scene when used).
    overflow (len(SEARCHED_SETS),) int64 on the device: queries (or cell visits) beyond capacity, accumulated.
    """

    capacities: dict[str, NeighborCapacity]
    topology_index: Tensor
    topology_valid: Tensor
    overflow: Tensor = field(repr=False)

    @classmethod
    def for_topology(cls, capacities: dict[str, NeighborCapacity], ti: Tensor, tj: Tensor, n: int) -> FixedNeighbors:
        missing = [s for s in SEARCHED_SETS if s not in capacities]
        if missing:
            raise ValueError(f"neighbour capacities missing for {missing} (have {sorted(capacities)})")
        index, valid = padded_pairs(ti, tj, n)
        return cls(dict(capacities), index, valid, torch.zeros(len(SEARCHED_SETS), dtype=torch.long, device=ti.device))

    def search(self, queries: dict[str, PairQuery]) -> dict[str, PaddedNeighbors]:
        """Padded neighbours per named set; adds each set's overflow to `self.overflow` in place (no sync)."""
        out = {}
        for k, name in enumerate(SEARCHED_SETS):
            q = queries[name]
            found = padded_radius_neighbors(q.query, q.points, q.radius, self.capacities[name], query_batch=q.query_batch,
                                            point_batch=q.point_batch, scenes=q.scenes, exclude_self=q.exclude_self)
            self.overflow[k] += found.overflow
            out[name] = found
        return out

    def topology(self, scenes: int) -> tuple[Tensor, Tensor]:
        """Padded topology of `scenes` scenes flattened: (scenes * N, Kt) indices into the flattened vertices, valid."""
        n = self.topology_index.shape[0]
        shift = (torch.arange(scenes, device=self.topology_index.device) * n)[:, None, None]
        index = (self.topology_index[None] + shift).reshape(scenes * n, -1)
        return index, self.topology_valid[None].expand(scenes, -1, -1).reshape(scenes * n, -1)

    def overflowed(self) -> dict[str, int]:
        """Overflow count per set since the last `reset` (reads the device: a sync)."""
        return {name: int(c) for name, c in zip(SEARCHED_SETS, self.overflow.tolist()) if c}

    def reset(self) -> None:
        self.overflow.zero_()

    def grown(self, sets: list[str], factor: float = 2.0) -> FixedNeighbors:
        """A copy whose capacities of `sets` are `factor` times larger (a new static shape: recompile / recapture)."""
        capacities = {name: capacity_for(int(c.max_neighbors * factor) if name in sets else c.max_neighbors,
                                         int(c.cell_capacity * factor) if name in sets else c.cell_capacity, 1.0)
                      for name, c in self.capacities.items()}
        return replace(self, capacities=capacities, overflow=torch.zeros_like(self.overflow))


def capacities_to_dict(capacities: dict[str, NeighborCapacity]) -> dict[str, list[int]]:
    """JSON form {set: [K, cell capacity]} (checkpoint configs)."""
    return {name: [c.max_neighbors, c.cell_capacity] for name, c in capacities.items()}


def capacities_from_dict(d: dict[str, list[int]]) -> dict[str, NeighborCapacity]:
    """Inverse of `capacities_to_dict`."""
    try:
        return {name: NeighborCapacity(int(k), int(c)) for name, (k, c) in d.items()}
    except (TypeError, ValueError) as err:
        raise ValueError(f"neighbour capacities must map set -> [K, cell capacity], got {d!r}") from err
