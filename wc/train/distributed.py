"""Process group set-up for `torchrun` (DistributedDataParallel) and the few agreements its ranks need; a plain run
is rank 0 of 1 and every helper here is then a no-op."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class Processes:
    rank: int
    world_size: int
    device: torch.device

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def start(device: str) -> Processes:
    """Join the torchrun group if WORLD_SIZE > 1 (NCCL on CUDA, gloo on CPU); pick this process's device."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world == 1:
        return Processes(0, 1, torch.device(device))
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    on_cuda = device.startswith("cuda")
    if on_cuda:
        torch.cuda.set_device(local)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if on_cuda else "gloo")
    return Processes(rank, world, torch.device(f"cuda:{local}") if on_cuda else torch.device("cpu"))


def barrier(procs: Processes) -> None:
    if procs.distributed:
        dist.barrier()


def stop(procs: Processes) -> None:
    if procs.distributed and dist.is_initialized():
        dist.destroy_process_group()


def world_size() -> int:
    """Processes in this run's group (1 without one)."""
    return dist.get_world_size() if dist.is_initialized() else 1


def summed(values: torch.Tensor) -> torch.Tensor:
    """`values` summed over the ranks (in place); itself in a plain run. What makes every rank take the same branch
    on a step's status (a non-finite loss, a neighbour overflow, the end of a chunk)."""
    if world_size() > 1:
        dist.all_reduce(values)
    return values


def any_rank(flag: bool, device: torch.device) -> bool:
    """Whether `flag` holds on any rank (e.g. one rank ran out of its time budget)."""
    return bool(summed(torch.tensor([float(flag)], device=device)).item() > 0)


def gathered(procs: Processes, value: Any) -> list[Any]:
    """Every rank's `value` (picklable), in rank order, on every rank; [value] in a plain run."""
    if not procs.distributed:
        return [value]
    out: list[Any] = [None] * procs.world_size
    dist.all_gather_object(out, value)
    return out
