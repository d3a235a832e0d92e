"""The executor switch of the three data stages (`agent.executor`, `expand.executor`, `render.executor`), the
`ray` params section that the `ray` executor reads (wc.distributed.executors) and the `processes` section that the
`processes` executor reads (wc.distributed.processes; also where `expand.shards` run)."""

from __future__ import annotations

import math
from dataclasses import dataclass

EXECUTORS = ("local", "ray", "processes")


def check_executor(name: object, key: str = "executor") -> None:
    """The one rule for a stage's `executor` value: local, ray or processes; else ValueError naming `key` and the
    value."""
    if name not in EXECUTORS:
        raise ValueError(f"{key} must be local, ray or processes, got {name!r}")


def uses_cuda(*devices: str) -> bool:
    """Whether a unit run with these params `device` values runs on a GPU (and the ray executor asks for one);
    `auto` asks for none."""
    return any(d.startswith("cuda") for d in devices)


@dataclass(frozen=True)
class RayConfig:
    """Where and how the `ray` executor runs work units (what a unit is: each stage's docstring)."""

    address: str | None = None  # ray.init address ("auto", "ray://head:10001"); null: $RAY_ADDRESS, else a new
    # Ray instance on this machine, stopped when the stage ends
    max_retries: int = 2  # a unit whose worker raised or died runs again at most this many times
    cpus_per_unit: float = 1.0  # CPUs a unit asks for (Newton's and the renderer's CPU kernels use one core)
    gpus_per_unit: float = 1.0  # GPUs a unit on a CUDA device asks for; a fraction shares one (0.25: four at once)

    def validate(self) -> None:
        if self.address is not None and not self.address.strip():
            raise ValueError(f"address must be null or a Ray address such as auto or ray://host:10001, "
                             f"got {self.address!r}")
        if self.max_retries < 0:
            raise ValueError(f"max_retries must be >= 0, got {self.max_retries}")
        if not (math.isfinite(self.cpus_per_unit) and self.cpus_per_unit > 0):
            raise ValueError(f"cpus_per_unit must be positive, got {self.cpus_per_unit}")
        gpus = self.gpus_per_unit
        if not (math.isfinite(gpus) and gpus > 0 and (gpus <= 1 or gpus.is_integer())):
            raise ValueError(f"gpus_per_unit must be a fraction in (0, 1] or a whole number of GPUs, got {gpus}")


@dataclass(frozen=True)
class ProcessesConfig:
    """How many device processes the `processes` executor starts (wc.distributed.processes)."""

    devices: int = 0  # processes, process k pinned to visible GPU k (mod the GPU count); 0: one per visible GPU, or
    # DEFAULT_CPU_PROCESSES where there is none

    def validate(self) -> None:
        if isinstance(self.devices, bool) or self.devices < 0:
            raise ValueError(f"devices must be >= 0 (0: one process per visible GPU), got {self.devices}")
