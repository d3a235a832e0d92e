"""Repeatable GPU runs on request: `WC_DETERMINISTIC=run_to_run` (or `gpu_to_gpu`) in the environment makes Warp's
floating-point atomics sum in a fixed order (`wp.config.deterministic`, Warp >= 1.15) and torch use its deterministic
kernels, so the same inputs give bit-identical results run after run on the same GPU architecture (`gpu_to_gpu`: across
architectures too). Unset or `off`: the default, faster ordering; CPU runs are repeatable either way.

An environment variable, not a param: a warp kernel module takes its options when it is defined (at import), before
any params are read, and spawned worker processes inherit it. `wc.warp_settings` applies it on import.
"""

from __future__ import annotations

import os

import warp as wp

ENV = "WC_DETERMINISTIC"
MODES = {"off": wp.DeterministicMode.NOT_GUARANTEED, "run_to_run": wp.DeterministicMode.RUN_TO_RUN,
         "gpu_to_gpu": wp.DeterministicMode.GPU_TO_GPU}
CUBLAS_WORKSPACE = ":4096:8"  # what torch's deterministic cuBLAS calls need (set before cuBLAS starts)


def requested_mode() -> str:
    """The mode named by WC_DETERMINISTIC ('off' when unset); a clear error for any other value."""
    mode = os.environ.get(ENV, "off").strip().lower() or "off"
    if mode not in MODES:
        raise ValueError(f"{ENV}={os.environ[ENV]!r}: expected one of {', '.join(MODES)}")
    return mode


def apply(mode: str) -> None:
    """Warp's atomics and torch's kernels in `mode`; call before kernel modules are defined."""
    wp.config.deterministic = MODES[mode]
    if mode == "off":
        return
    import torch

    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE)
    torch.use_deterministic_algorithms(True, warn_only=True)  # an op without such a kernel warns, naming itself


def active_mode() -> str:
    """The mode warp runs in now (recorded beside timings: deterministic atomics cost time)."""
    return next(name for name, value in MODES.items() if value == wp.config.deterministic)
