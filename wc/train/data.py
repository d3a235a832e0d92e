"""Training windows: W-frame segments of stored episodes, grouped by scene layout.

A hand-off episode (a held ball released into the bag) has two layouts: before its release frame
the ball is prescribed (its samples ride on the `held_<name>` body and its rows leave x), from the
release frame on it is predicted (paper: an object moves from B_t to S_t). Each such part is a
*phase*; windows never straddle phases, and one batch holds windows of one layout.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from wc.data.store import TrajectoryStore

LayoutKey = tuple[tuple[str, ...], tuple[str, ...]]  # (predicted objects, prescribed link columns)


@dataclass(frozen=True)
class Phase:
    """Frames [start, stop) of an episode that share one layout."""

    episode: str
    start: int
    stop: int
    layout: LayoutKey


@dataclass(frozen=True)
class Window:
    """A W-frame segment [start, start + W) inside one phase."""

    phase: Phase
    start: int


def episode_phases(store: TrajectoryStore, eid: str) -> list[Phase]:
    """The episode's phases: one, or two around a hand-off's release frame (which both share)."""
    objects, links = store.episode_objects(eid), store.episode_links(eid)
    frames = store.num_frames(eid)
    handoff = store.episode_attrs(eid).get("handoff") or {}
    if not handoff:
        return [Phase(eid, 0, frames, (tuple(objects), tuple(links)))]
    release = int(min(handoff.values()))
    held = {f"held_{name}" for name in handoff}
    before = (tuple(o for o in objects if o not in handoff), tuple(links))
    after = (tuple(objects), tuple(l for l in links if l not in held))
    return [Phase(eid, 0, release + 1, before), Phase(eid, release, frames, after)]


def layout_phase_start(store: TrajectoryStore, phase: Phase) -> int:
    """The first frame of the episode's phase (episode_phases) of `phase`'s layout that holds it: a held-out block
    is part of one. The frames from there to `phase.start` are recorded in the same layout."""
    for whole in episode_phases(store, phase.episode):
        if whole.layout == phase.layout and whole.start <= phase.start < whole.stop:
            return whole.start
    return phase.start


def phases_of(store: TrajectoryStore, split: str) -> list[Phase]:
    """Phases of every episode in `split`."""
    return [p for eid in store.episodes_where(split=split) for p in episode_phases(store, eid)]


def split_blocks(phases: list[Phase], fraction: float, block_frames: int, window: int
                 ) -> tuple[list[Phase], list[Phase]]:
    """(train, held-out) phases: each phase cut into `block_frames` blocks, every k-th block held out (k = 1/fraction).

    Interleaving (rather than holding out each episode's tail) keeps every kind of motion — a fall,
    an impact, a lift — on both sides when each task has one episode. Block 0 always trains; runs of
    training blocks merge; held blocks shorter than `window` are dropped, so no frame is on both sides.
    """
    every = max(2, int(round(1.0 / fraction)))
    train, held = [], []
    for p in phases:
        cuts = list(range(p.start, p.stop, block_frames)) + [p.stop]
        run_start = p.start
        for i, (a, b) in enumerate(zip(cuts, cuts[1:])):
            if i % every != every - 1:
                continue
            if a - run_start >= window:
                train.append(Phase(p.episode, run_start, a, p.layout))
            if b - a >= window:
                held.append(Phase(p.episode, a, b, p.layout))
            run_start = b
        if p.stop - run_start >= window:
            train.append(Phase(p.episode, run_start, p.stop, p.layout))
    return train, held


def windows_of(phases: list[Phase], window: int) -> list[Window]:
    """Every W-frame window inside the phases."""
    return [Window(p, s) for p in phases for s in range(p.start, p.stop - window + 1)]


def read_phase_window(store: TrajectoryStore, phase: Phase, start: int, length: int) -> dict[str, np.ndarray]:
    """x, v (length, N, 3) of the phase's objects and poses (length, P, 7) of its links then environment bodies."""
    arrays = store.read_window(phase.episode, start, length)
    layout = store.episode_layout(phase.episode)
    rows = np.concatenate([np.arange(layout[o].start, layout[o].stop) for o in phase.layout[0]])
    links = store.episode_links(phase.episode)
    cols = [links.index(name) for name in phase.layout[1]]
    poses = np.concatenate([arrays["link_poses"][:, cols], arrays["env_poses"]], axis=1)
    return {"x": arrays["x"][:, rows], "v": arrays["v"][:, rows], "poses": poses, "action": arrays["action"]}


class WindowDataset(Dataset[dict[str, torch.Tensor]]):
    """Windows as a map-style dataset.

    item = {x, v (W, N, 3), poses (W, P, 7), action (W, 14), layout ()}: `layout` indexes `layout_keys`.
    """

    def __init__(self, store_path: str | os.PathLike[str], windows: list[Window], length: int) -> None:
        if not windows:
            raise ValueError(f"{store_path}: no {length}-frame training window")
        self.store_path = Path(store_path)
        self.windows = windows
        self.length = length
        self.layout_keys: list[LayoutKey] = list(dict.fromkeys(w.phase.layout for w in windows))
        self._layout_index = {k: i for i, k in enumerate(self.layout_keys)}
        self._store: TrajectoryStore | None = None

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        if self._store is None:
            self._store = TrajectoryStore(self.store_path)
        w = self.windows[i]
        arrays = read_phase_window(self._store, w.phase, w.start, self.length)
        item = {k: torch.from_numpy(np.ascontiguousarray(a)) for k, a in arrays.items()}
        return {**item, "layout": torch.tensor(self._layout_index[w.phase.layout])}

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_store": None}  # workers open their own handle


class LayoutBatchSampler(torch.utils.data.Sampler[list[int]]):
    """Endless seeded batches of `batch_size` window indices, each batch from one layout.

    A layout is drawn with probability proportional to its window count (or its windows' summed `weights`), then
    windows uniformly (or in proportion to `weights`, e.g. wc.train.events); `rank` gives each process of a
    distributed run its own stream of windows. With `shared_layouts` (a run of several processes) the layouts come
    from a stream every rank shares, so all ranks step through the same layout's static step together (a captured
    gradient all-reduce must be replayed by every rank in the same graph); alone, one stream draws both.
    """

    SHARED = 2**31 - 1  # the layout stream's key beside the seed (never a rank)

    def __init__(self, windows: list[Window], batch_size: int, seed: int, rank: int = 0,
                 weights: np.ndarray | None = None, shared_layouts: bool = False) -> None:
        if weights is not None and (len(weights) != len(windows) or not (np.asarray(weights) > 0).all()):
            raise ValueError(f"sampling weights must be {len(windows)} positive values, one per window")
        groups: dict[LayoutKey, list[int]] = {}
        for i, w in enumerate(windows):
            groups.setdefault(w.phase.layout, []).append(i)
        self.groups = [np.asarray(g) for g in groups.values()]
        window_w = np.ones(len(windows)) if weights is None else np.asarray(weights, dtype=np.float64)
        mass = np.array([window_w[g].sum() for g in self.groups])
        self.weights = mass / mass.sum()
        self.within = None if weights is None else [window_w[g] / window_w[g].sum() for g in self.groups]
        self.batch_size = batch_size
        self.rng = np.random.default_rng([seed, rank])
        self.layout_rng = np.random.default_rng([seed, self.SHARED]) if shared_layouts else self.rng

    def state(self) -> dict:
        """The sampler's position in its streams (checkpointed for an exact resume)."""
        if self.layout_rng is self.rng:
            return self.rng.bit_generator.state
        return {"windows": self.rng.bit_generator.state, "layouts": self.layout_rng.bit_generator.state}

    def set_state(self, state: dict) -> None:
        if (self.layout_rng is self.rng) != ("layouts" not in state):
            raise ValueError("training state: its sampler was saved with a different number of processes")
        if self.layout_rng is self.rng:
            self.rng.bit_generator.state = state
        else:
            self.rng.bit_generator.state = state["windows"]
            self.layout_rng.bit_generator.state = state["layouts"]

    def __iter__(self):  # noqa: ANN204 - infinite iterator
        while True:
            g = self.layout_rng.choice(len(self.groups), p=self.weights)
            group = self.groups[g]
            if self.within is None:
                yield group[self.rng.integers(0, len(group), size=self.batch_size)].tolist()
            else:
                yield group[self.rng.choice(len(group), size=self.batch_size, p=self.within[g])].tolist()


Scale = float | tuple[float, float, float]  # one value, or one per axis (x, y, z)


@dataclass(frozen=True)
class Scales:
    """Data scales: velocity features are divided by `velocity_m_s`; the head's outputs are in units of the deltas."""

    velocity_m_s: Scale
    delta_x_m: Scale
    delta_v_m_s: Scale


def overall(scale: Scale) -> float:
    """One value of a (possibly per-axis) scale: the RMS over its axes."""
    return float(np.sqrt(np.mean(np.square(scale))))


def data_scales(store: TrajectoryStore, phases: list[Phase], max_episodes: int, per_axis: bool = False) -> Scales:
    """RMS of v, of per-frame Δx and of per-frame Δv over (up to `max_episodes`) training phases; per axis (x, y, z)
    when `per_axis`, else one RMS over the three (per component)."""
    picked = phases[:: max(1, len(phases) // max_episodes)][:max_episodes]
    v2, dx2, dv2 = np.zeros(3), np.zeros(3), np.zeros(3)
    count = moves = 0
    for p in picked:
        a = read_phase_window(store, p, p.start, p.stop - p.start)
        x, v = a["x"].astype(np.float64), a["v"].astype(np.float64)
        v2 += (v ** 2).reshape(-1, 3).sum(0)
        count += v.size // 3
        dx2 += (np.diff(x, axis=0) ** 2).reshape(-1, 3).sum(0)
        dv2 += (np.diff(v, axis=0) ** 2).reshape(-1, 3).sum(0)
        moves += v[1:].size // 3
    if count == 0 or moves == 0:
        raise ValueError(f"{store.path}: no frames to measure data scales from")
    floor = 1e-6  # a static dataset (or axis) still gets finite scales

    def rms(sum_sq: np.ndarray, n: int) -> Scale:
        if per_axis:
            return tuple(float(a) for a in np.maximum(np.sqrt(sum_sq / n), floor))
        return max(float(np.sqrt(sum_sq.sum() / (3 * n))), floor)

    return Scales(velocity_m_s=rms(v2, count), delta_x_m=rms(dx2, moves), delta_v_m_s=rms(dv2, moves))
