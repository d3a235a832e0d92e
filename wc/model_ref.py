"""Where a saved model is, and what a report records of it. One resolver for every place that takes a model path
(`train.init_from`, `expand --model`, `evaluate.methods.<m>.path`, `load_model`). A reference is one of

    models/pretrained/worldcontact-lift-handle            a model folder (model.safetensors + model.json in it)
    models/worldcontact/model.safetensors                 a weights file (its .json beside it)
    hf://owner/repo[/folder][@revision]                   a model folder in a Hugging Face Hub repo
    hf://owner/repo/path/name.safetensors[@revision]      a weights file in a hub repo (its .json beside it)

Hub files are downloaded into the Hugging Face cache (HF_HUB_OFFLINE=1: read from the cache only).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

HUB_PREFIX = "hf://"
WEIGHTS = "model.safetensors"
HUB_FORM = "hf://owner/repo[/folder][/name.safetensors][@revision]"


def is_hub_ref(ref: str | os.PathLike[str]) -> bool:
    return isinstance(ref, str) and ref.startswith(HUB_PREFIX)


def _hub_weights(ref: str, what: str) -> Path:
    from huggingface_hub import hf_hub_download  # noqa: PLC0415 - only hub references need it

    location, _, revision = ref[len(HUB_PREFIX):].partition("@")
    parts = location.strip("/").split("/")
    if len(parts) < 2 or not all(parts) or parts[1].endswith(".safetensors"):
        raise ValueError(f"{what} {ref!r}: a hub model is {HUB_FORM}")
    repo, rest = "/".join(parts[:2]), "/".join(parts[2:])
    filename = rest if rest.endswith(".safetensors") else f"{rest}/{WEIGHTS}" if rest else WEIGHTS
    try:
        weights = hf_hub_download(repo, filename, revision=revision or None)
        hf_hub_download(repo, str(Path(filename).with_suffix(".json")), revision=revision or None)
    except Exception as err:  # offline misses, unknown repos and files all raise their own types
        raise FileNotFoundError(f"{what} {ref!r}: not available from the hub or its cache: {err}") from err
    return Path(weights)


def resolve_weights(ref: str | os.PathLike[str], what: str = "model") -> Path:
    """The local .safetensors file `ref` names (module docstring), downloading a hub model when needed.
    FileNotFoundError naming `what` (the param or flag that gave `ref`) when it is not there; ValueError for a
    malformed hub reference."""
    if is_hub_ref(ref):
        return _hub_weights(str(ref), what)
    path = Path(ref)
    if path.is_dir():
        path = path / WEIGHTS
    if not path.is_file():
        raise FileNotFoundError(f"{what}: checkpoint not found: {path} (a model folder holding {WEIGHTS} and "
                                "model.json, or a .safetensors file with its .json)")
    return path


def resolve_model_dir(ref: str | os.PathLike[str], what: str = "model") -> Path:
    """The local folder holding model.safetensors + model.json that `ref` names (a hub model is downloaded).
    A weights file of another name is an error: stages read model folders."""
    weights = resolve_weights(ref, what)
    if weights.name != WEIGHTS:
        raise ValueError(f"{what} {str(ref)!r}: a model folder holds {WEIGHTS}, not {weights.name}")
    return weights.parent


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def model_record(ref: str | os.PathLike[str], weights: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """What a report records of the model it used: the reference as given (`path`), the SHA-256 of its weights file
    (`weights` when already resolved, else resolved from `ref`) and, from its .json when there is one, the training
    params hash, step and stage. The hash names the weights even after the path holds others."""
    weights = Path(weights) if weights is not None else resolve_weights(ref)
    record: dict[str, Any] = {"path": str(ref), "sha256": file_sha256(weights)}
    config = weights.with_suffix(".json")
    if config.is_file():
        meta = json.loads(config.read_text())
        record.update({k: meta.get(k) for k in ("params_hash", "step", "stage") if k in meta})
    return record
