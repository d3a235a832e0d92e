"""Training segments: fixed-length frame windows [start, start + window) of stored episodes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from wc.data.store import EPISODE_ARRAYS, TrajectoryStore

Segment = tuple[str, int]  # (episode id, start frame)


def enumerate_segments(store: TrajectoryStore, window: int, *, split: str | None = None,
                       task: str | None = None) -> list[Segment]:
    """All (episode, start) with start + window <= T, over episodes matching split/task (None = any)."""
    if window < 1:
        raise ValueError(f"window must be >= 1 frame, got {window}")
    eids = store.episodes_where(split=split, task=task)
    segments = [(e, s) for e in eids for s in range(store.num_frames(e) - window + 1)]
    if not segments:
        raise ValueError(f"{store.path}: no {window}-frame window in {len(eids)} episode(s) "
                         f"matching split={split!r}, task={task!r}")
    return segments


class SegmentSampler:
    """Uniform sampling (with replacement) over every valid window; reproducible from `seed`."""

    def __init__(self, store: TrajectoryStore, window: int, *, split: str | None = None,
                 task: str | None = None, seed: int) -> None:
        self.window = window
        self.segments = enumerate_segments(store, window, split=split, task=task)
        self._rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.segments)

    def sample(self, n: int) -> list[Segment]:
        """`n` segments; successive calls continue the seeded stream."""
        return [self.segments[i] for i in self._rng.integers(0, len(self.segments), size=n)]


class SegmentDataset(Dataset[dict[str, torch.Tensor]]):
    """Every window of a store as a map-style dataset; item = {x, v, action, link_poses, env_poses}.

    Shapes: x, v (window, N_e, 3); action (window, 14); link_poses (window, L_e, 7);
    env_poses (window, E, 7); all float32, with N_e and L_e those of the segment's episode
    (`TrajectoryStore.episode_layout`): batch segments of one task, or pad, when they differ.
    The store opens lazily in each DataLoader worker.
    """

    def __init__(self, store_path: str | os.PathLike[str], window: int, split: str | None = None, *,
                 task: str | None = None, fields: tuple[str, ...] = EPISODE_ARRAYS) -> None:
        self.store_path = Path(store_path)
        self.window = window
        self.fields = fields
        self.segments = enumerate_segments(TrajectoryStore(store_path), window, split=split, task=task)
        self._store: TrajectoryStore | None = None

    def __len__(self) -> int:
        return len(self.segments)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        if self._store is None:
            self._store = TrajectoryStore(self.store_path)
        eid, start = self.segments[i]
        arrays = self._store.read_window(eid, start, self.window, self.fields)
        return {k: torch.from_numpy(a) for k, a in arrays.items()}

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_store": None}  # workers open their own handle
