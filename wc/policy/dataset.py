"""Write a LeRobot v3 dataset of right-arm episodes from trajectory stores and their rendered frames.

Frame k holds the state at t = k·dt (fps = 1/dt). The robot is kinematic: at frame k it is AT
store action[k] and it moves to action[k+1] during frame k -> k+1. So, per frame k of an episode:

    observation.state[k]         = action[k, 7:14]    where the right arm is: q_R (6, rad), d_R (m)
    action[k]                    = action[k+1, 7:14]  the command that moves it during the next frame
                                                      (the last frame repeats its own: hold still)
    observation.images.<cam>[k]  = rendered frame k of camera <cam> (top, wrist)

hence action[k] == observation.state[k + 1] within an episode. Videos are encoded by lerobot's own
writer (`LeRobotDataset.create` -> `add_frame` -> `save_episode` -> `finalize`) into a temporary
sibling directory that is renamed into place once the dataset is complete; with `dataset.workers` > 1,
contiguous shards of the episodes are written side by side and joined in order (wc.policy.dataset_shards).
"""

from __future__ import annotations

import json
import shutil
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from wc.atomic import remove_stale_temporaries, temporary_sibling
from wc.data.store import ACTION_DIM, TrajectoryStore
from wc.policy.dataset_config import DatasetConfig
from wc.policy.video_frame_check import missing_video_frames
from wc.policy.video_roundtrip import video_encoder
from wc.render.frames import RenderedStore
from wc.reports import replace_dir

RIGHT_ARM = slice(7, 14)  # columns of the store action: q_R (6, rad), d_R (m)
CAMERAS = {"top": "observation.images.top", "wrist": "observation.images.wrist"}  # rendered camera -> feature
STATE_NAMES = [f"right_joint_{i}_rad" for i in range(1, 7)] + ["right_gripper_opening_m"]
PROVENANCE_FILE = "meta/worldcontact_episodes.json"  # episode_index -> store and episode id
CARD_FILE = "README.md"
VIDEO_BACKEND = "pyav"  # decoder for read-back checks: torchcodec may be installed yet unloadable on CPU hosts
FPS_TOLERANCE = 1e-6  # 1/dt must be an integer to this relative tolerance (LeRobot stores an int fps)


@dataclass(frozen=True)
class EpisodeSource:
    """One episode to write: its trajectory store (`store_name` says which, e.g. source) and rendered frames."""

    store_name: str
    trajectories: TrajectoryStore
    frames: RenderedStore
    episode_id: str


def right_arm_state_action(action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(observation.state, action), both (T, 7) float32, from a store's action (T, 14); see the module doc."""
    action = np.asarray(action)
    if action.ndim != 2 or action.shape[1] != ACTION_DIM or len(action) < 1:
        raise ValueError(f"store action must have shape (T >= 1, {ACTION_DIM}), got {action.shape}")
    state = action[:, RIGHT_ARM].astype(np.float32)
    return state, np.concatenate([state[1:], state[-1:]], axis=0)


def fps_of(dt: float) -> int:
    """Integer frames per second for a frame interval `dt` (s); raises if 1/dt is not an integer."""
    fps = 1.0 / dt
    if round(fps) < 1 or abs(fps - round(fps)) > FPS_TOLERANCE * fps:
        raise ValueError(f"frame dt {dt} s gives fps {fps}, not an integer: LeRobot datasets need an integer fps")
    return int(round(fps))


def dataset_features(height: int, width: int) -> dict[str, dict[str, Any]]:
    """LeRobot feature spec: two RGB videos (height, width, 3), a 7-D right-arm state and action."""
    image = {"dtype": "video", "shape": (height, width, 3), "names": ["height", "width", "channels"]}
    vector = {"dtype": "float32", "shape": (len(STATE_NAMES),), "names": list(STATE_NAMES)}
    return {**{feature: dict(image) for feature in CAMERAS.values()},
            "observation.state": dict(vector), "action": dict(vector)}


def select_episodes(store_name: str, trajectories: TrajectoryStore, frames: RenderedStore, task: str,
                    splits: Sequence[str] | None = None) -> tuple[list[EpisodeSource], dict[str, int]]:
    """Accepted episodes of `task` (in `splits`, or all when None), checked against the rendered store,
    and the counts of episodes left out ({"other_task": n, "split": n, "rejected": n})."""
    cams = [c for c in CAMERAS if c not in frames.cameras]
    if cams:
        raise ValueError(f"rendered store {frames.path} has no camera(s) {cams}; it has {frames.cameras}")
    rendered_fps, fps = float(frames.attrs["fps"]), 1.0 / trajectories.dt
    if abs(rendered_fps - fps) > FPS_TOLERANCE * fps:
        raise ValueError(f"rendered store {frames.path} has fps {rendered_fps} but trajectory store "
                         f"{trajectories.path} has dt {trajectories.dt} s (fps {fps}): were they made together?")
    rendered = set(frames.episode_ids())
    chosen, skipped = [], {"other_task": 0, "split": 0, "rejected": 0}
    for eid in trajectories.episode_ids:
        attrs = trajectories.episode_attrs(eid)
        reason = ("other_task" if attrs["task"] != task else "split" if splits is not None and attrs["split"] not in splits
                  else "rejected" if attrs["accepted"] is not True else None)
        if reason:
            skipped[reason] += 1
            continue
        if eid not in rendered:
            raise ValueError(f"episode {eid} of {trajectories.path} has no rendered frames in {frames.path} "
                             "(re-run the render stage)")
        n_traj = trajectories.num_frames(eid)
        n_rendered = int(frames.episode_attrs(eid)["frames"])
        if n_rendered != n_traj:
            raise ValueError(f"episode {eid}: {n_traj} frames in {trajectories.path} but {n_rendered} rendered "
                             f"frames in {frames.path} (re-run the render stage)")
        chosen.append(EpisodeSource(store_name, trajectories, frames, eid))
    return chosen, skipped


def _image_size(episodes: Sequence[EpisodeSource]) -> tuple[int, int]:
    """(height, width) shared by every rendered store of `episodes`; raises if they differ."""
    sizes = {(int(e.frames.attrs["height"]), int(e.frames.attrs["width"])): e.frames.path for e in episodes}
    if len(sizes) != 1:
        raise ValueError(f"rendered stores differ in image size (height, width): {sizes}; one dataset needs one size")
    return next(iter(sizes))


def create_dataset(root: Path, repo_id: str, fps: int, height: int, width: int, cfg: DatasetConfig) -> Any:
    """An empty LeRobotDataset at `root` with the dataset stage's features and video encoder."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset.create(repo_id, fps=fps, features=dataset_features(height, width), root=root,
                                 robot_type=cfg.robot_type, use_videos=True, rgb_encoder=video_encoder(cfg),
                                 encoder_threads=cfg.encoder_threads or None,
                                 streaming_encoding=False, video_backend=VIDEO_BACKEND)  # streaming drops frames


def write_episodes(root: Path, repo_id: str, fps: int, height: int, width: int, cfg: DatasetConfig,
                   episodes: Sequence[EpisodeSource], desc: str | None) -> int:
    """Write `episodes` in order as a new LeRobot dataset at `root`, one after the other; returns the frame count.
    `desc` labels the progress bar (None: no bar)."""
    ds = create_dataset(root, repo_id, fps, height, width, cfg)
    frames = 0
    for e in tqdm(episodes, desc=desc, unit="episode", disable=desc is None):
        state, action = right_arm_state_action(e.trajectories.read_episode(e.episode_id, ("action",))["action"])
        images = {cam: e.frames.frames(e.episode_id, cam) for cam in CAMERAS}
        for k in range(len(state)):
            ds.add_frame({"observation.state": state[k], "action": action[k], "task": cfg.instruction,
                          **{feature: images[cam][k] for cam, feature in CAMERAS.items()}})
        ds.save_episode(parallel_encoding=False)  # one process per dataset (or shard): cores go to the shards
        frames += len(state)
    ds.finalize()
    return frames


def _check_target(path: Path) -> None:
    """Refuse to replace anything but a LeRobot dataset (meta/info.json) or an empty directory."""
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise FileExistsError(f"{path} exists and is not a directory; refusing to replace it")
    if path.is_dir() and any(path.iterdir()) and not (path / "meta" / "info.json").is_file():
        raise FileExistsError(f"{path} is a non-empty directory that is not a LeRobot dataset; refusing to replace it")


def _replace_dir(tmp: Path, path: Path) -> None:
    """Rename the finished `tmp` to `path`, replacing a previous dataset there."""
    _check_target(path)
    replace_dir(tmp, path)


def _provenance(episodes: Sequence[EpisodeSource]) -> list[dict[str, Any]]:
    """One row per LeRobot episode_index: which store and trajectory episode it came from."""
    rows = []
    for index, e in enumerate(episodes):
        a = e.trajectories.episode_attrs(e.episode_id)
        rows.append({"episode_index": index, "store": e.store_name, "trajectories": str(e.trajectories.path),
                     "episode_id": e.episode_id, "frames": e.trajectories.num_frames(e.episode_id),
                     **{k: a.get(k) for k in ("task", "split", "source", "seed", "cell", "speed", "amplitude")}})
    return rows


def write_lerobot_dataset(out: str | Path, repo_id: str, episodes: Sequence[EpisodeSource], cfg: DatasetConfig,
                          card: Callable[[dict[str, Any]], str]) -> dict[str, Any]:
    """Write `episodes` as a LeRobot v3 dataset at `out` (atomically) with a dataset card README.md made by
    `card(summary)`; returns the summary {repo_id, path, episodes, frames, fps, image_size, wall_s, ...}."""
    out = Path(out)
    if not episodes:
        raise ValueError(f"no episodes to write to {out}")
    _check_target(out)
    dts = {e.trajectories.dt for e in episodes}
    if len(dts) != 1:
        raise ValueError(f"trajectory stores differ in frame dt {sorted(dts)} s; one dataset needs one fps")
    fps = fps_of(dts.pop())
    height, width = _image_size(episodes)
    started = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out)
    tmp, scratch = temporary_sibling(out), temporary_sibling(out)
    try:
        if cfg.workers > 1 and len(episodes) > 1:
            from wc.policy.dataset_shards import write_shards  # it builds on this module's writer

            frames = write_shards(tmp, scratch, repo_id, fps, height, width, cfg, list(episodes))
        else:
            frames = write_episodes(tmp, repo_id, fps, height, width, cfg, episodes, f"dataset {out.name}")
        missing = missing_video_frames(tmp)
        if missing:
            raise RuntimeError(f"dataset {out.name}: frames missing from the encoded videos ({len(missing)} episode "
                               f"videos), e.g. {missing[0]}")
        provenance = _provenance(episodes)
        (tmp / PROVENANCE_FILE).write_text(json.dumps(provenance, indent=1) + "\n")
        per_store = Counter(row["store"] for row in provenance)
        summary = {"repo_id": repo_id, "path": str(out), "episodes": len(episodes), "frames": frames, "fps": fps,
                   "image_size": [height, width], "instruction": cfg.instruction, "task": cfg.task,
                   "robot_type": cfg.robot_type, "video_codec": cfg.video_codec,
                   "stores": sorted(per_store), "episodes_per_store": dict(sorted(per_store.items()))}
        (tmp / CARD_FILE).write_text(card(summary))
        _replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    summary["wall_s"] = time.perf_counter() - started
    return summary


def check_loads(path: str | Path, repo_id: str, episodes: int, frames: int) -> None:
    """Open `path` with stock `LeRobotDataset` and check its episode and frame counts (no hub access)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=path, video_backend=VIDEO_BACKEND)
    if ds.num_episodes != episodes or ds.num_frames != frames:
        raise RuntimeError(f"{path}: LeRobot reads {ds.num_episodes} episodes / {ds.num_frames} frames, "
                           f"expected {episodes} / {frames}")
