"""The torch device a params `device` key names."""

from __future__ import annotations

import torch


def resolve_device(name: str, key: str) -> torch.device:
    """torch device of params `key` (e.g. "evaluate.device") = `name`; auto: CUDA when present."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"{key} is {name!r} but CUDA is not available")
    return torch.device(name)
