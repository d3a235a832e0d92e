"""Params of the `dataset` stage (`dataset:` in params.yaml): which episodes go into the LeRobot
datasets, their task string and how the camera videos are encoded."""

from __future__ import annotations

import re
from dataclasses import dataclass

from wc.data.store import SPLITS

VIDEO_CODECS = ("libsvtav1", "h264", "hevc", "libaom-av1")  # software encoders lerobot 0.6.1 accepts
_REPO_RE = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclass(frozen=True)
class DatasetConfig:
    task: str  # trajectory-store task whose episodes go in, e.g. lift_handle
    instruction: str  # LeRobot task string of every frame, e.g. "right grasp and lift"
    splits: tuple[str, ...]  # source-store splits that go in (expanded episodes go in whatever their split)
    robot_type: str  # LeRobot metadata robot_type
    repo_owner: str  # local repo ids are <repo_owner>/source and <repo_owner>/expanded
    include_expanded: bool  # false: build the source dataset only (before the expand and render stages exist)
    require_generated: bool  # true: no generated episode in the expanded store is an error (no hollow comparison)
    video_codec: str  # one of VIDEO_CODECS; lerobot's default is libsvtav1
    video_crf: int  # codec quality (lower: better and larger)
    video_gop_frames: int  # keyframe interval; small keeps random frame access cheap
    encoder_threads: int  # threads per video encoder (0: let the codec decide)
    expanded_arm: str = "expanded"  # name of the dataset source + expanded-store episodes; another name builds a
    # control arm from another store, e.g. newton_150 = the source + fresh Newton episodes (policy comparison)
    workers: int = 1  # processes writing a dataset's episodes side by side (shards joined by lerobot's aggregation)

    def validate(self) -> None:
        for name in ("task", "instruction", "robot_type"):
            if not getattr(self, name).strip():
                raise ValueError(f"dataset.{name} must be a non-empty string")
        if not self.splits:
            raise ValueError("dataset.splits must name at least one split")
        bad = [s for s in self.splits if s not in SPLITS or s is None]
        if bad or len(set(self.splits)) != len(self.splits):
            raise ValueError(f"dataset.splits must be distinct names from {[s for s in SPLITS if s]}, got "
                             f"{list(self.splits)}")
        if not _REPO_RE.match(self.expanded_arm) or self.expanded_arm == "source":
            raise ValueError(f"dataset.expanded_arm must be letters, digits, '_', '.', '-' and not 'source', got "
                             f"{self.expanded_arm!r}")
        if not _REPO_RE.match(self.repo_owner):
            raise ValueError(f"dataset.repo_owner must be letters, digits, '_', '.', '-', got {self.repo_owner!r}")
        if self.video_codec not in VIDEO_CODECS:
            raise ValueError(f"dataset.video_codec must be one of {VIDEO_CODECS}, got {self.video_codec!r}")
        if not 0 <= self.video_crf <= 63:
            raise ValueError(f"dataset.video_crf must be in [0, 63], got {self.video_crf}")
        if self.video_gop_frames < 1:
            raise ValueError(f"dataset.video_gop_frames must be >= 1, got {self.video_gop_frames}")
        if self.workers < 1:
            raise ValueError(f"dataset.workers must be >= 1, got {self.workers}")
        if self.encoder_threads < 0:
            raise ValueError(f"dataset.encoder_threads must be >= 0, got {self.encoder_threads}")
