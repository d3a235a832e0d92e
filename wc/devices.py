"""The device a params `device` key names: a torch device, or a warp device string."""

from __future__ import annotations

import torch
import warp as wp


def resolve_device(name: str, key: str) -> torch.device:
    """torch device of params `key` (e.g. "evaluate.device") = `name`; auto: CUDA when present."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"{key} is {name!r} but CUDA is not available")
    return torch.device(name)


def resolve_warp_device(name: str, key: str) -> str:
    """warp device of params `key` (e.g. "sim.device") = `name`; auto: 'cuda:0' when warp sees a CUDA device."""
    if name == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise RuntimeError(f"{key} is {name!r} but no CUDA device is available (use cpu or auto)")
    if not (name == "cpu" or name.startswith("cuda")):
        raise ValueError(f"{key} must be cpu, cuda[:N] or auto, got {name!r}")
    return name
