"""Episode videos: frames (T, H, W, 3) uint8 RGB -> mp4 (OpenCV's mp4v encoder)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from wc.atomic import write_atomic


def write_mp4(path: str | Path, frames: Sequence[np.ndarray], fps: float) -> Path:
    """Write RGB frames (H, W, 3) uint8 as an mp4 at `path` (temporary sibling, then renamed)."""
    path = Path(path)
    if not len(frames):
        raise ValueError(f"{path}: no frames to write")
    return write_atomic(path, lambda tmp: _encode(tmp, frames, fps, path), keep_suffix=True)


def _encode(tmp: Path, frames: Sequence[np.ndarray], fps: float, path: Path) -> None:
    """Encode `frames` into the mp4 file `tmp` (errors name the target `path`)."""
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height))
    try:
        if not writer.isOpened():
            raise RuntimeError(f"OpenCV cannot open an mp4v writer for {tmp}")
        for frame in frames:
            if frame.shape != (height, width, 3) or frame.dtype != np.uint8:
                raise ValueError(f"{path}: frames must all be ({height}, {width}, 3) uint8, got {frame.shape} "
                                 f"{frame.dtype}")
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
