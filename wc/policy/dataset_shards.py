"""One LeRobot dataset written by several processes (`dataset.workers` > 1).

The episodes are cut into contiguous shards; a spawned process writes each shard as a LeRobot dataset with the
stage's encoder (`wc.policy.dataset.write_episodes`), and lerobot's own `aggregate_datasets` joins the shards in
episode order: the videos and parquet files concatenated by stream copy (no re-encoding), the per-episode
statistics merged. lerobot's `save_episode(parallel_encoding=True)` encodes only one episode's cameras side by
side; an episode's image statistics, which cost more than its encoding at 128 x 128, stay serial there.
"""

from __future__ import annotations

from concurrent.futures import as_completed
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from wc.data.store import TrajectoryStore
from wc.policy.dataset import EpisodeSource, write_episodes
from wc.policy.dataset_config import DatasetConfig
from wc.render.frames import RenderedStore
from wc.worker_pool import spawn_pool


@dataclass(frozen=True)
class EpisodeRef:
    """An EpisodeSource by its stores' paths, for a worker process to open."""

    store_name: str
    trajectories: str
    frames: str
    episode_id: str


def shard_bounds(n: int, shards: int) -> list[tuple[int, int]]:
    """[start, stop) of at most `shards` contiguous, near-equal, non-empty slices of `n` items, in order."""
    if n < 1 or shards < 1:
        raise ValueError(f"shard_bounds needs n >= 1 and shards >= 1, got n={n}, shards={shards}")
    shards = min(shards, n)
    cuts = [round(i * n / shards) for i in range(shards + 1)]
    return list(zip(cuts[:-1], cuts[1:]))


def _write_shard(root: str, repo_id: str, fps: int, height: int, width: int, cfg: DatasetConfig,
                 refs: list[EpisodeRef]) -> int:
    """Worker: open the stores of `refs` and write them as a LeRobot dataset at `root`; returns the frame count."""
    trajectories = {p: TrajectoryStore(p) for p in {r.trajectories for r in refs}}
    frames = {p: RenderedStore(p) for p in {r.frames for r in refs}}
    episodes = [EpisodeSource(r.store_name, trajectories[r.trajectories], frames[r.frames], r.episode_id) for r in refs]
    return write_episodes(Path(root), repo_id, fps, height, width, cfg, episodes, desc=None)


def write_shards(root: Path, scratch: Path, repo_id: str, fps: int, height: int, width: int, cfg: DatasetConfig,
                 episodes: list[EpisodeSource]) -> int:
    """Write `episodes` as one LeRobot dataset at `root` (which must not exist) from shards written side by side
    by `cfg.workers` processes under `scratch` (left for the caller to remove); returns the frame count."""
    from lerobot.datasets.aggregate import aggregate_datasets

    refs = [EpisodeRef(e.store_name, str(e.trajectories.path), str(e.frames.path), e.episode_id) for e in episodes]
    bounds = shard_bounds(len(refs), cfg.workers)
    roots = [scratch / f"shard-{k:03d}" for k in range(len(bounds))]
    scratch.mkdir(parents=True)
    frames = 0
    with spawn_pool(len(bounds)) as pool:
        futures = [pool.submit(_write_shard, str(r), repo_id, fps, height, width, cfg, refs[a:b])
                   for r, (a, b) in zip(roots, bounds)]
        for future in tqdm(as_completed(futures), total=len(futures), desc=f"dataset {root.name}: shards",
                           unit="shard"):
            frames += future.result()
    aggregate_datasets([repo_id] * len(roots), repo_id, roots=roots, aggr_root=root)
    return frames
