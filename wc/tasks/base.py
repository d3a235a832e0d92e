"""Task programs: an initial-state sampler + an action program a_t from (cell, speed, amplitude).

Tasks register by name, so adding one is one new module under wc/tasks/ that calls
`register_task`; `wc.tasks.get_task` imports them all.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np

from wc.dynamics import ObjectState
from wc.scene.scene import Scene


UNREACHABLE = "unreachable"  # the outcome of an episode whose program could not be planned (no IK solution)


class InfeasibleEpisode(ValueError):
    """The task cannot plan this episode (e.g. a target out of the robot's reach)."""


@dataclass(frozen=True)
class EpisodeSpec:
    """What the agent chose for one episode."""

    task: str
    seed: int
    cell: int
    speed: float  # task-specific speed scale [m/s]
    amplitude: float  # task-specific motion amplitude [m]


class Task(Protocol):
    """Reset = initial_state -> settle (if `settle`) -> prepare; Execute = actions, open loop."""

    name: ClassVar[str]
    objects: ClassVar[tuple[str, ...]]  # predicted objects this task's scene needs
    settle: ClassVar[bool]  # let the objects come to rest before frame 0
    handoff: ClassVar[tuple[str, ...]]  # held objects that become predicted when their gripper opens

    def num_cells(self) -> int: ...

    def speed_range(self) -> tuple[float, float]: ...

    def amplitude_range(self) -> tuple[float, float]: ...

    def initial_state(self, scene: Scene, spec: EpisodeSpec, rng: np.random.Generator) -> ObjectState:
        """Objects placed for the episode, before settling."""
        ...

    def settle_action(self, scene: Scene, spec: EpisodeSpec, initial: ObjectState) -> np.ndarray:
        """(14,) robot posture held while the objects settle; also frame 0's action."""
        ...

    def prepare(self, scene: Scene, settled: ObjectState, spec: EpisodeSpec, rng: np.random.Generator
                ) -> ObjectState:
        """Frame 0's state from the settled one."""
        ...

    def held(self) -> dict[str, tuple[str, np.ndarray]]:
        """Objects held from the start: name -> (link, local pose (7,))."""
        ...

    def actions(self, scene: Scene, settled: ObjectState, spec: EpisodeSpec, start: np.ndarray,
                frame_dt_s: float) -> np.ndarray:
        """(T, 14) commanded actions from frame 0 (the prepared state, action `start`) on; open loop."""
        ...

    def check(self, scene: Scene, spec: EpisodeSpec, x: np.ndarray, action: np.ndarray) -> str | None:
        """Task-level verdict on a finished episode (None = did what it should)."""
        ...


_REGISTRY: dict[str, tuple[type, type]] = {}


def register_task(name: str, config_cls: type):
    """Class decorator: register a task under `name` with its params dataclass."""

    def wrap(cls: type) -> type:
        cls.name = name
        _REGISTRY[name] = (cls, config_cls)
        return cls

    return wrap


def task_names() -> list[str]:
    _import_all()
    return sorted(_REGISTRY)


def get_task(name: str, params: dict[str, Any]) -> Task:
    """Instantiate task `name` from its section `tasks.<name>` (+ the shared `tasks.common`)."""
    from wc.config import load_section
    from wc.tasks.common import CommonTaskConfig

    _import_all()
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}; known tasks: {sorted(_REGISTRY)}")
    cls, config_cls = _REGISTRY[name]
    scoped = {"_source": params.get("_source", "<params>"),
              **{f"tasks.{k}": v for k, v in (params.get("tasks") or {}).items()}}  # errors name tasks.<x>.<key>
    return cls(load_section(scoped, f"tasks.{name}", config_cls), load_section(scoped, "tasks.common", CommonTaskConfig))


def _import_all() -> None:
    import importlib
    import pkgutil

    import wc.tasks

    for module in pkgutil.iter_modules(wc.tasks.__path__):
        if module.name != "base":
            importlib.import_module(f"wc.tasks.{module.name}")
