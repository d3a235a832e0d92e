"""The device a params `device` key names: a torch device, or a warp device string."""

from __future__ import annotations

import re

import torch
import wc.warp_settings  # noqa: F401  (first: kernels take warp's settings when defined)
import warp as wp

_DEVICE = re.compile(r"^(cpu|auto|cuda(:\d+)?)$")


def check_device_name(name: object, key: str = "device", allow_auto: bool = True) -> None:
    """The one rule for a params `device` value: cpu, cuda, cuda:N or (where `allow_auto`) auto; else ValueError
    naming `key`."""
    if not isinstance(name, str) or not _DEVICE.match(name) or (name == "auto" and not allow_auto):
        choices = "cpu, cuda, cuda:N" + (" or auto" if allow_auto else "")
        raise ValueError(f"{key} must be {choices}, got {name!r}")


def resolve_device(name: str, key: str) -> torch.device:
    """torch device of params `key` (e.g. "evaluate.device") = `name`; auto: CUDA when present."""
    check_device_name(name, key)
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"{key} is {name!r} but CUDA is not available")
    return torch.device(name)


def resolve_warp_device(name: str, key: str) -> str:
    """warp device of params `key` (e.g. "sim.device") = `name`; auto: 'cuda:0' when warp sees a CUDA device."""
    check_device_name(name, key)
    if name == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise RuntimeError(f"{key} is {name!r} but no CUDA device is available (use cpu or auto)")
    return name
