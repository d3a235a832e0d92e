"""A pretrained WorldContact to start training from (`train.init_from`): a local checkpoint (the `.safetensors`
file with its `.json` sibling, or a directory holding model.safetensors) or a Hugging Face Hub file
`hf://owner/repo/path/model.safetensors[@revision]` (downloaded with its .json; HF_HUB_OFFLINE=1 reads the cache)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from huggingface_hub import hf_hub_download

from wc.model.config import ModelConfig
from wc.model.worldcontact import WorldContact
from wc.train.checkpoint import load_model

HUB_PREFIX = "hf://"
ROLLOUT_ONLY = ("neighbor_skin_m",)  # model keys that do not change the network: they may differ from the checkpoint


def resolve_checkpoint(ref: str) -> Path:
    """The local weights file that `ref` names, downloading a hub file (and its .json) when needed."""
    if ref.startswith(HUB_PREFIX):
        location, _, revision = ref[len(HUB_PREFIX):].partition("@")
        parts = location.split("/")
        if len(parts) < 3 or not all(parts):
            raise ValueError(f"train.init_from {ref!r}: a hub file is hf://owner/repo/path/model.safetensors[@revision]")
        repo, filename = "/".join(parts[:2]), "/".join(parts[2:])
        try:
            weights = hf_hub_download(repo, filename, revision=revision or None)
            hf_hub_download(repo, str(Path(filename).with_suffix(".json")), revision=revision or None)
        except Exception as err:  # offline misses, unknown repos and files all raise their own types
            raise FileNotFoundError(f"train.init_from {ref!r}: not available from the hub or its cache: {err}") from err
        return Path(weights)
    path = Path(ref)
    if path.is_dir():
        path = path / "model.safetensors"
    if not path.is_file():
        raise FileNotFoundError(f"train.init_from: checkpoint not found: {path}")
    return path


def pretrained_model(ref: str, model_cfg: ModelConfig) -> tuple[WorldContact, dict[str, Any]]:
    """The checkpoint `ref` names, in train mode, with its config; ValueError naming the `model` params that differ
    from the checkpoint's architecture (the network and its data scales come from the checkpoint)."""
    model, config = load_model(resolve_checkpoint(ref))
    ours, theirs = model_cfg.to_dict(), model.config.to_dict()
    differ = [f"{k}: params {ours[k]!r} vs checkpoint {theirs[k]!r}" for k in ours
              if k not in ROLLOUT_ONLY and ours[k] != theirs.get(k)]
    if differ:
        raise ValueError(f"train.init_from {ref!r}: the model section differs from the checkpoint's ({'; '.join(differ)});"
                         " set those model params to the checkpoint's values, or clear train.init_from")
    return model.train(), config
