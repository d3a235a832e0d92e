"""What the task programs share: the `tasks.common` params and a base class for cells and ranges."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.scene import Scene
from wc.tasks.base import EpisodeSpec
from wc.tasks.motion import IKSettings


@dataclass(frozen=True)
class CommonTaskConfig:
    """`tasks.common`: the gripper, IK and bag-placement settings every task program uses."""

    bag_center_xy_m: tuple[float, float]
    bag_jitter_m: float  # uniform xy jitter of the initial bag position
    drop_height_m: float  # bag bottom above the table top before settling
    open_m: float  # gripper opening while approaching
    closed_m: float  # commanded opening when pinching
    close_s: float  # time to close or open the gripper
    start_height_m: float  # TCP distance back along the approach axis while the objects settle
    approach_height_m: float  # pre-grasp TCP distance back along the approach axis
    approach_tilt_deg: float  # approach axis tilted from vertical, away from the arm's base
    ik_iterations: int
    ik_tolerance_m: float  # a plan whose IK misses by more is infeasible
    ik_tolerance_rad: float

    def validate(self) -> None:
        if not 0 <= self.closed_m < self.open_m:
            raise ValueError(f"need 0 <= closed_m < open_m, got {self.closed_m}, {self.open_m}")
        if self.close_s <= 0 or self.ik_iterations < 1:
            raise ValueError("close_s and ik_iterations must be positive")

    def bag_centre(self, rng: np.random.Generator) -> np.ndarray:
        """The bag's initial xy centre, jittered uniformly by bag_jitter_m."""
        return np.asarray(self.bag_center_xy_m) + rng.uniform(-1, 1, 2) * self.bag_jitter_m

    @property
    def ik(self) -> IKSettings:
        return IKSettings(self.ik_iterations, self.ik_tolerance_m, self.ik_tolerance_rad)


def check_range(name: str, value: tuple[float, float], low_may_be_zero: bool = False) -> None:
    """A (low, high) param must satisfy 0 < low <= high (0 <= low when allowed)."""
    lo, hi = value
    if not ((0 <= lo if low_may_be_zero else 0 < lo) and lo <= hi):
        raise ValueError(f"{name} must satisfy {'0 <=' if low_may_be_zero else '0 <'} low <= high, got {value}")


class TaskProgram:
    """Base of the task programs: cells are the product of the bins named in `BINS`; speed and
    amplitude ranges come from the config's `speed_range` / `amplitude_range` fields."""

    name: ClassVar[str]
    objects: ClassVar[tuple[str, ...]] = ("bag",)
    BINS: ClassVar[tuple[str, ...]] = ()  # config fields whose product makes the coverage cells
    settle: ClassVar[bool] = True  # let the objects come to rest before frame 0
    handoff: ClassVar[tuple[str, ...]] = ()  # held objects that become predicted when their gripper opens

    def __init__(self, config: Any, common: CommonTaskConfig):
        self.cfg, self.common = config, common
        for name in self.BINS:
            if not getattr(config, name):
                raise ValueError(f"tasks.{self.name}.{name} must list at least one bin")

    def num_cells(self) -> int:
        return int(np.prod([len(getattr(self.cfg, b)) for b in self.BINS]))

    def cell_values(self, cell: int) -> dict[str, Any]:
        """The bin values of a cell, by field name."""
        combos = list(itertools.product(*(getattr(self.cfg, b) for b in self.BINS)))
        return dict(zip(self.BINS, combos[cell % len(combos)]))

    def speed_range(self) -> tuple[float, float]:
        return tuple(self.cfg.speed_range_m_s)

    def amplitude_range(self) -> tuple[float, float]:
        return tuple(self.cfg.amplitude_range_m)

    def held(self) -> dict[str, tuple[str, np.ndarray]]:
        """Objects the robot holds from the start: name -> (link, local pose (7,))."""
        return {}

    def prepare(self, scene: Scene, settled: ObjectState, spec: EpisodeSpec, rng: np.random.Generator
                ) -> ObjectState:
        """Frame 0's state from the settled one (e.g. lift a parked object to where it is dropped)."""
        return settled

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """A task-level verdict on a finished episode: None, or why it did not do what it should."""
        return None
