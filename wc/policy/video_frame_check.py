"""Every frame of a LeRobot dataset's episodes is in its videos.

lerobot's streaming encoder (`streaming_encoding=True`) drops a frame whenever its queue is full (it is made for live
capture); a dataset built offline with it lost one frame in some runs, and training then failed deep inside lerobot's
video decoder ("query timestamps unexpectedly violate the tolerance"). The dataset stage therefore encodes after each
episode and checks, before the dataset is published, that each episode's span of each video file decodes to as many
frames as the episode has.
"""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq


def _frame_times(video: Path) -> np.ndarray:
    """Presentation times [s] of every decoded frame of `video`."""
    with av.open(str(video)) as container:
        return np.array([float(frame.time) for frame in container.decode(video=0)])


def missing_video_frames(root: str | Path) -> list[str]:
    """One line per (episode, camera) whose span of its video file does not decode to the episode's frame count, for
    the LeRobot v3 dataset at `root`; [] when every frame is there."""
    root = Path(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    fps = float(info["fps"])
    keys = [k for k, f in info["features"].items() if f.get("dtype") == "video"]
    parts = sorted((root / "meta" / "episodes").rglob("*.parquet"))
    episodes = pa.concat_tables([pq.read_table(p) for p in parts]).to_pylist() if parts else []
    half = 0.5 / fps
    times: dict[Path, np.ndarray] = {}
    problems = []
    for ep in episodes:
        for key in keys:
            video = root / info["video_path"].format(video_key=key, chunk_index=ep[f"videos/{key}/chunk_index"],
                                                     file_index=ep[f"videos/{key}/file_index"])
            if video not in times:
                times[video] = _frame_times(video) if video.is_file() else np.zeros(0)
            t = times[video]
            start, end = ep[f"videos/{key}/from_timestamp"], ep[f"videos/{key}/to_timestamp"]
            found = int(((t >= start - half) & (t < end - half)).sum())
            if found != ep["length"]:
                problems.append(f"{video.relative_to(root)}: episode {ep['episode_index']} has {found} of its "
                                f"{ep['length']} frames between {start:.3f} and {end:.3f} s")
    return problems
