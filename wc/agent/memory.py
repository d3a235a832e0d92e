"""The agent's failure memory: every episode outcome, kept across runs in one JSON file.

Outcomes are filed under a `task_key`, a string the caller derives from the task's configuration
(e.g. a hash of its params), so outcomes of a differently configured task are never reused.
The file only grows: outcomes are appended, never edited.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from wc.reports import write_json_atomic
from wc.tasks.base import EpisodeSpec

SCHEMA = "worldcontact-agent-memory/1"
MODES = ("fresh", "kept")  # agent.memory: where a simulate run's planner starts (FailureMemory.for_run)


@dataclass(frozen=True)
class Outcome:
    """One episode the agent ran, and its verdict."""

    task: str
    task_key: str  # the task's configuration; outcomes are reused only under the same key
    cell: int
    speed: float  # as in EpisodeSpec [m/s]
    amplitude: float  # as in EpisodeSpec [m]
    seed: int
    failure: str | None  # first failing predicate; None: accepted
    failure_frame: int | None = None  # frame of the first failure, where known


_FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "task": (str,), "task_key": (str,), "cell": (int,), "speed": (int, float), "amplitude": (int, float),
    "seed": (int,), "failure": (str, type(None)), "failure_frame": (int, type(None)),
}
_OPTIONAL = {"failure_frame"}


class FailureMemory:
    """Outcomes in the order they were recorded, indexed by task key and cell."""

    def __init__(self, path: str | Path | None = None, outcomes: Iterable[Outcome] = ()) -> None:
        self.path = Path(path) if path is not None else None  # None: kept in memory only
        self._all: list[Outcome] = []
        self._by_key: dict[str, list[Outcome]] = {}
        self._by_cell: dict[tuple[str, int], list[Outcome]] = {}
        for outcome in outcomes:
            self._add(outcome)

    @classmethod
    def load(cls, path: str | Path) -> FailureMemory:
        """The memory stored at `path`; empty if the file does not exist yet. Malformed file: ValueError."""
        path = Path(path)
        if not path.exists():
            return cls(path)
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ValueError(f"{path}: agent memory is not valid JSON ({err}); fix or delete the file") from err
        if not isinstance(data, dict) or data.get("schema") != SCHEMA:
            found = data.get("schema") if isinstance(data, dict) else type(data).__name__
            raise ValueError(f"{path}: not an agent memory file (schema {found!r}, expected {SCHEMA!r})")
        if not isinstance(data.get("outcomes"), list):
            raise ValueError(f"{path}: 'outcomes' must be a list")
        return cls(path, (_parse_outcome(entry, f"{path}: outcomes[{i}]") for i, entry in enumerate(data["outcomes"])))

    @classmethod
    def for_run(cls, path: str | Path | None, mode: str) -> FailureMemory:
        """The memory a simulate run starts from and saves to `path` (None: none). mode fresh: no outcomes, so
        the run's episodes depend on its params and seed alone and the file is rewritten with this run's;
        kept: the file's (`load`), appended to."""
        if mode not in MODES:
            raise ValueError(f"agent memory mode must be fresh or kept, got {mode!r}")
        return cls.load(path) if mode == "kept" and path is not None else cls(path)

    def record(self, task_key: str, spec: EpisodeSpec, failure: str | None,
               failure_frame: int | None = None) -> Outcome:
        """Append the outcome of episode `spec` (not saved until `save`)."""
        outcome = Outcome(spec.task, task_key, spec.cell, float(spec.speed), float(spec.amplitude), spec.seed,
                          failure, failure_frame)
        self._add(outcome)
        return outcome

    def outcomes(self, task_key: str, cell: int | None = None) -> list[Outcome]:
        """Outcomes under `task_key` (only of `cell`, if given), oldest first."""
        found = self._by_key.get(task_key, []) if cell is None else self._by_cell.get((task_key, cell), [])
        return list(found)

    def visits(self, task_key: str) -> Counter[int]:
        """Episodes run per cell under `task_key`."""
        return Counter(o.cell for o in self._by_key.get(task_key, []))

    def accepted(self, task_key: str) -> Counter[int]:
        """Accepted episodes per cell under `task_key`."""
        return Counter(o.cell for o in self._by_key.get(task_key, []) if o.failure is None)

    def save(self) -> Path:
        """Write every outcome to `path` atomically (a reader never sees a half-written file)."""
        if self.path is None:
            raise ValueError("this agent memory has no file to save to; give FailureMemory a path")
        return write_json_atomic(self.path, {"schema": SCHEMA, "outcomes": [asdict(o) for o in self._all]})

    def __len__(self) -> int:
        return len(self._all)

    def _add(self, outcome: Outcome) -> None:
        self._all.append(outcome)
        self._by_key.setdefault(outcome.task_key, []).append(outcome)
        self._by_cell.setdefault((outcome.task_key, outcome.cell), []).append(outcome)


def _parse_outcome(entry: Any, where: str) -> Outcome:
    """One stored outcome, checked field by field; `where` names it in errors."""
    if not isinstance(entry, dict):
        raise ValueError(f"{where} must be a mapping, got {entry!r}")
    unknown = sorted(set(entry) - set(_FIELD_TYPES))
    missing = sorted(set(_FIELD_TYPES) - _OPTIONAL - set(entry))
    if unknown or missing:
        raise ValueError(f"{where}: unknown keys {unknown}, missing keys {missing}")
    for name, value in entry.items():
        # bool is an int to isinstance, but never a valid value here
        if isinstance(value, bool) or not isinstance(value, _FIELD_TYPES[name]):
            raise ValueError(f"{where}.{name} has the wrong type: {value!r}")
    for name in ("speed", "amplitude"):
        if not math.isfinite(entry[name]):
            raise ValueError(f"{where}.{name} must be finite, got {entry[name]!r}")
    return Outcome(**{**entry, "speed": float(entry["speed"]), "amplitude": float(entry["amplitude"])})
