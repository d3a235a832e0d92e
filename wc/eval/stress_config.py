"""The `stress` params section: named stress cases (a task + params overrides), their ground-truth episodes,
the rollout horizon and the side-by-side video."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from wc.devices import check_device_name

OVERRIDABLE = ("tasks", "sim")  # a case may change the task programs and the physics, not the scene meshes


def check_override_keys(overrides: dict[str, Any], where: str) -> None:
    """Each key is a dotted params path under one of OVERRIDABLE, e.g. sim.bag.density_kg_m2."""
    for key in overrides:
        parts = str(key).split(".")
        if len(parts) < 2 or parts[0] not in OVERRIDABLE or not all(parts):
            raise ValueError(f"{where}.{key}: an override key must be a dotted path under one of {OVERRIDABLE}, "
                             "e.g. sim.bag.density_kg_m2")


@dataclass(frozen=True)
class StressCase:
    """One stress case: episodes of `task` (default: stress.task) simulated with `overrides` applied on top of
    stress.overrides (dotted params keys -> values)."""

    task: str | None = None
    overrides: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        check_override_keys(self.overrides, "overrides")


@dataclass(frozen=True)
class VideoConfig:
    """Side-by-side video of one case's first episode: ground truth | `method` | the best of `baselines`."""

    case: str  # a stress case name
    method: str  # an evaluate.methods name (WorldContact)
    baselines: tuple[str, ...]  # evaluate.methods names; the one with the lowest position MSE in the metrics is shown
    frames: int  # at most this many frames (<= 100)
    panel_px: int  # width and height of each panel [px]
    sheet_frames: int  # frames per row of the contact-sheet PNG
    camera: str = "top"  # a scene.cameras name
    device: str = "cpu"  # renderer: cpu | cuda | auto

    def validate(self) -> None:
        if not 2 <= self.frames <= 100:
            raise ValueError(f"frames must be in [2, 100], got {self.frames}")
        for name in ("panel_px", "sheet_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.baselines:
            raise ValueError("baselines must name at least one method")
        check_device_name(self.device)


@dataclass(frozen=True)
class StressConfig:
    """Stress cases beyond the training distribution: Newton ground truth, every evaluate method rolled out."""

    task: str  # task of a case that names none
    episodes: int  # ground-truth episodes per case
    max_attempts: int  # draws per case at most (unplannable or physically insane episodes are redrawn)
    rollout_frames: int  # steps from frame 0; the simulation is cut there too
    cases: dict[str, StressCase]
    video: VideoConfig
    overrides: dict[str, Any] = field(default_factory=dict)  # applied to every case, before its own
    seed: int = 0
    workers: int = 1  # cases simulated at once, one spawned process each (the episodes do not depend on it)
    device: str = "cpu"  # model rollouts: cpu | cuda | cuda:k | auto
    methods: tuple[str, ...] | None = None  # evaluate.methods names rolled out; None: every one on disk

    def validate(self) -> None:
        for name in ("episodes", "rollout_frames", "workers"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_attempts < self.episodes:
            raise ValueError(f"max_attempts ({self.max_attempts}) must be >= episodes ({self.episodes})")
        if not self.cases:
            raise ValueError("cases is empty: name at least one stress case")
        check_override_keys(self.overrides, "overrides")
        if self.methods is not None:
            if not self.methods:
                raise ValueError("methods is empty: name evaluate.methods entries, or null for all of them")
            if self.video.method not in self.methods:
                raise ValueError(f"video.method {self.video.method!r} is not one of methods {list(self.methods)}")
        if self.video.case not in self.cases:
            raise ValueError(f"video.case {self.video.case!r} is not one of cases {sorted(self.cases)}")
        check_device_name(self.device)

    def case_task(self, name: str) -> str:
        return self.cases[name].task or self.task
