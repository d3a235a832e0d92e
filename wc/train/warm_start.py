"""A pretrained WorldContact to start training from (`train.init_from`): any model reference of wc/model_ref.py (a
model folder, a `.safetensors` file with its `.json` sibling, or a Hugging Face Hub model `hf://owner/repo[/folder]`
or file `hf://owner/repo/path/model.safetensors[@revision]`; HF_HUB_OFFLINE=1 reads the cache)."""

from __future__ import annotations

from typing import Any

from wc.model.config import ModelConfig
from wc.model.worldcontact import WorldContact
from wc.model_ref import resolve_weights
from wc.train.checkpoint import load_model

ROLLOUT_ONLY = ("neighbor_skin_m",)  # model keys that do not change the network: they may differ from the checkpoint


def pretrained_model(ref: str, model_cfg: ModelConfig) -> tuple[WorldContact, dict[str, Any]]:
    """The checkpoint `ref` names, in train mode, with its config; ValueError naming the `model` params that differ
    from the checkpoint's architecture (the network and its data scales come from the checkpoint)."""
    model, config = load_model(resolve_weights(ref, "train.init_from"))
    ours, theirs = model_cfg.to_dict(), model.config.to_dict()
    differ = [f"{k}: params {ours[k]!r} vs checkpoint {theirs[k]!r}" for k in ours
              if k not in ROLLOUT_ONLY and ours[k] != theirs.get(k)]
    if differ:
        raise ValueError(f"train.init_from {ref!r}: the model section differs from the checkpoint's ({'; '.join(differ)});"
                         " set those model params to the checkpoint's values, or clear train.init_from")
    return model.train(), config
