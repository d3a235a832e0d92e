"""Params of the render stage (`render:` in params.yaml)."""

from __future__ import annotations

from dataclasses import dataclass

from wc.devices import check_device_name
from wc.distributed.config import check_executor


@dataclass(frozen=True)
class RenderConfig:
    width: int  # [px], every camera (overrides scene.cameras.*.width)
    height: int  # [px]
    device: str  # "cpu", "cuda", "cuda:0", or "auto" (cuda when present)
    cameras: tuple[str, ...]  # names in scene.cameras, in store order
    tasks: tuple[str, ...] | None  # render only these tasks' episodes; null = every episode
    frames_per_batch: int  # frames rendered per SensorCamera call (one model world per frame)
    shadows: bool  # shadow rays from the key light (about 1.5x the cost)
    sheet_frames: int  # contact sheet: frames per episode and camera, evenly spaced
    sheet_episodes: int  # contact sheet: at most this many episodes (first ones of the first store)
    executor: str = "local"  # local: in this process; ray / processes: `episodes_per_unit` episodes per unit
    episodes_per_unit: int = 4  # episodes one work unit renders (the frames do not depend on it)

    def validate(self) -> None:
        check_executor(self.executor)
        for name in ("width", "height", "frames_per_batch", "sheet_frames", "sheet_episodes", "episodes_per_unit"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be a positive integer, got {getattr(self, name)}")
        if not self.cameras or len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras must be distinct names, got {list(self.cameras)}")
        if self.tasks is not None and not self.tasks:
            raise ValueError("tasks must list at least one task, or be null for every episode")
        check_device_name(self.device)
