"""A work-unit worker for the processes executor's pinning test (tests/test_processes_executor.py), in a module that
imports no test module (one importing tests.test_simulate_workers initialises warp's CUDA runtime)."""

from __future__ import annotations

import os
from collections.abc import Callable


def pinned_view(_: str) -> Callable[[int], tuple[str | None, bool, int]]:
    """A worker reporting its process's GPU pin, whether CUDA is initialised once the stages' modules are imported,
    and its pid."""
    import stages.expand  # noqa: F401  (the heaviest imports: Newton, warp, torch, the model)
    import stages.simulate  # noqa: F401
    from wc.distributed.processes import cuda_initialised

    return lambda payload: (os.environ.get("CUDA_VISIBLE_DEVICES"), cuda_initialised(), os.getpid())
