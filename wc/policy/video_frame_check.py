"""Every frame of a LeRobot dataset's episodes is in its videos.

lerobot's streaming encoder (`streaming_encoding=True`) drops a frame whenever its queue is full (it is made for live
capture); a dataset built offline with it lost one frame in some runs, and training then failed deep inside lerobot's
video decoder ("query timestamps unexpectedly violate the tolerance"). The dataset stage therefore encodes after each
episode and checks, before the dataset is published, that each episode's span of each video file decodes to as many
frames as the episode has.
"""

from __future__ import annotations

from pathlib import Path

import av
import numpy as np
from lerobot.datasets import LeRobotDatasetMetadata


def _frame_times(video: Path) -> np.ndarray:
    """Presentation times [s] of every decoded frame of `video`."""
    with av.open(str(video)) as container:
        return np.array([float(frame.time) for frame in container.decode(video=0)])


def missing_video_frames(root: str | Path) -> list[str]:
    """One line per (episode, camera) whose span of its video file does not decode to the episode's frame count, for
    the LeRobot v3 dataset at `root` (read through lerobot's metadata); [] when every frame is there."""
    root = Path(root)
    meta = LeRobotDatasetMetadata(f"local/{root.name}", root=root)
    half = 0.5 / float(meta.fps)
    times: dict[Path, np.ndarray] = {}
    problems = []
    for index in range(meta.total_episodes):
        ep = meta.episodes[index]
        for key in meta.video_keys:
            video = root / meta.get_video_file_path(index, key)
            if video not in times:
                times[video] = _frame_times(video) if video.is_file() else np.zeros(0)
            t = times[video]
            start, end = ep[f"videos/{key}/from_timestamp"], ep[f"videos/{key}/to_timestamp"]
            found = int(((t >= start - half) & (t < end - half)).sum())
            if found != ep["length"]:
                problems.append(f"{video.relative_to(root)}: episode {ep['episode_index']} has {found} of its "
                                f"{ep['length']} frames between {start:.3f} and {end:.3f} s")
    return problems
