"""Neural-dynamics baselines (RoboCraft, RoboCook, AdaptiGraph) behind the one rollout interface.

    model = load_baseline("models/baselines/robocraft")      # eval mode, CPU
    x, v = model.rollout(layout, x0, v0, poses, dt)           # (B, T-1, N, 3) for every mesh vertex

A saved baseline is a directory with model.safetensors (weights and data statistics) and
model.json (name, params, training metadata). README.md documents the choices.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from wc.atomic import write_atomic
from wc.baselines.adaptigraph import AdaptiGraph
from wc.baselines.base import ParticleDynamics
from wc.baselines.config import BaselineParams
from wc.baselines.robocook import RoboCook
from wc.baselines.robocraft import RoboCraft

BASELINES: dict[str, type[ParticleDynamics]] = {cls.name: cls for cls in (RoboCraft, RoboCook, AdaptiGraph)}
WEIGHTS, CONFIG = "model.safetensors", "model.json"

__all__ = ["BASELINES", "ParticleDynamics", "build_baseline", "load_baseline", "save_baseline"]


def build_baseline(name: str, params: BaselineParams) -> ParticleDynamics:
    """A freshly initialised baseline by registry name."""
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r} (known: {sorted(BASELINES)})")
    return BASELINES[name](params)


def save_baseline(model: ParticleDynamics, directory: str | os.PathLike[str], meta: dict[str, Any]) -> Path:
    """Write `directory`/model.safetensors and model.json (each atomically); returns the directory."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    write_atomic(directory / WEIGHTS, lambda p: save_file(state, str(p)))
    config = {"name": model.name, "params": dataclasses.asdict(model.params), **meta}
    write_atomic(directory / CONFIG, lambda p: p.write_text(json.dumps(config, indent=2, default=float)))
    return directory


def load_baseline(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> ParticleDynamics:
    """A trained baseline (eval mode) from its directory (or its model.safetensors / model.json)."""
    path = Path(path)
    directory = path if path.is_dir() else path.parent
    for p in (directory / WEIGHTS, directory / CONFIG):
        if not p.is_file():
            raise FileNotFoundError(f"baseline file missing: {p}")
    try:
        config = json.loads((directory / CONFIG).read_text())
        model = build_baseline(config["name"], BaselineParams(**config["params"]))
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"{directory / CONFIG}: not a baseline config: {err}") from err
    try:
        state = load_file(str(directory / WEIGHTS))
    except Exception as err:  # safetensors raises its own error types for corrupt files
        raise ValueError(f"{directory / WEIGHTS}: unreadable safetensors file: {err}") from err
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ValueError(f"{directory}: weights do not match {config['name']} (missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]})")
    return model.to(device).eval()
