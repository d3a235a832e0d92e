"""Checkpoints: weights as safetensors + a JSON config; optimizer/schedule state for resuming."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from wc.atomic import write_atomic
from wc.model.config import ModelConfig
from wc.model.worldcontact import WorldContact
from wc.model_ref import resolve_weights


def save_weights(model: WorldContact, path: Path, meta: dict[str, Any]) -> None:
    """Write `path` (.safetensors) and its sibling `<stem>.json` (model config, scales, `meta`)."""
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    write_atomic(path, lambda p: save_file(state, str(p)))
    config = {"model": model.config.to_dict(), "scales": model_scales(model), **meta}
    write_atomic(path.with_suffix(".json"), lambda p: p.write_text(json.dumps(config, indent=2)))


def model_scales(model: WorldContact) -> dict[str, float | list[float]]:
    """The model's data scales as WorldContact's keyword arguments (one value, or one per axis)."""
    v, dx, dv = (float(row[0]) if bool((row == row[0]).all()) else [float(a) for a in row] for row in model.scales)
    return {"velocity_m_s": v, "delta_x_m": dx, "delta_v_m_s": dv}


def load_model(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> tuple[WorldContact, dict[str, Any]]:
    """A WorldContact (eval mode) and its config dict from `path`: a model folder (model.safetensors + model.json), a
    .safetensors file with its sibling .json, or a Hugging Face Hub model hf://owner/repo[/folder] (wc/model_ref.py)."""
    path = resolve_weights(path, "load_model")
    config_path = path.with_suffix(".json")
    for p in (path, config_path):
        if not p.is_file():
            raise FileNotFoundError(f"checkpoint file missing: {p}")
    try:
        config = json.loads(config_path.read_text())
        model = WorldContact(ModelConfig(**config["model"]), **config["scales"])
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"{config_path}: not a WorldContact checkpoint config: {err}") from err
    try:
        state = load_file(str(path))
    except Exception as err:  # safetensors raises its own error types for corrupt files
        raise ValueError(f"{path}: unreadable safetensors file: {err}") from err
    if state.get("scales") is not None and state["scales"].shape == (3,):  # saved before per-axis scales
        state["scales"] = state["scales"][:, None].expand(3, 3).contiguous()
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ValueError(f"{path}: weights do not match the config (missing {missing[:3]}, unexpected {unexpected[:3]})")
    return model.to(device).eval(), config


def save_state(path: Path, state: dict[str, Any]) -> None:
    """Optimizer, scheduler, step, RNG and history for resuming (torch.save, atomic)."""
    write_atomic(path, lambda p: torch.save(state, p))


def load_state(path: Path) -> dict[str, Any]:
    """A `save_state` file; a clear error when it is unreadable (e.g. cut short by a lost job)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # torch raises several types for truncated or foreign files
        raise ValueError(f"{path}: unreadable training state ({err}); delete it to start afresh") from err


def rng_states(device: torch.device) -> dict[str, Any]:
    """The random streams a training run draws from (torch CPU, and the device's CUDA generator)."""
    states: dict[str, Any] = {"torch": torch.get_rng_state()}
    if device.type == "cuda":
        states["cuda"] = torch.cuda.get_rng_state(device)
    return states


def restore_rng_states(states: dict[str, Any], device: torch.device) -> None:
    """Inverse of `rng_states` (a CUDA state is restored only on a CUDA device)."""
    torch.set_rng_state(states["torch"])
    if device.type == "cuda" and "cuda" in states:
        torch.cuda.set_rng_state(states["cuda"], device)
