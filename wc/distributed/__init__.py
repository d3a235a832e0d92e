"""Executors for the data stages (simulate, expand, render): their work units run in this process (`local`), as
Ray tasks on a laptop, one GPU machine or a cluster (`ray`), or in one process per GPU of this host (`processes`),
with the same results either way."""

from wc.distributed.config import EXECUTORS, ProcessesConfig, RayConfig, check_executor, uses_cuda
from wc.distributed.executors import (Executor, LocalExecutor, RayExecutor, Unit, UnitFailure, UnitsFailed,
                                      WorkerSpec, every_unit, open_executor)
from wc.distributed.streams import Stream, drive

__all__ = ["EXECUTORS", "Executor", "LocalExecutor", "ProcessesConfig", "RayConfig", "RayExecutor", "Stream", "Unit",
           "UnitFailure", "UnitsFailed", "WorkerSpec", "check_executor", "drive", "every_unit", "open_executor",
           "uses_cuda"]
