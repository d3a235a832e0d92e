"""Local pretrained files, checked before and after lerobot loads them.

lerobot 0.6.1's `PI05Policy.from_pretrained` prints a warning and returns a randomly initialised
model when it cannot find or load `model.safetensors`; the checks here turn that into an error.
"""

from __future__ import annotations

from pathlib import Path

import torch

WEIGHTS_FILE = "model.safetensors"
TOKENIZER_FILES = ("tokenizer.json", "tokenizer.model", "tokenizer_config.json")
WEIGHT_SAMPLES = 16  # checkpoint tensors compared with the built policy


class PretrainedFilesError(FileNotFoundError):
    """A named local checkpoint or tokenizer is missing or unusable."""


def checkpoint_weights(path: str | Path, what: str = "policy.pretrained_path") -> Path:
    """The weights file of the local checkpoint directory `path` (named `what` in errors); raises if missing."""
    path = Path(path)
    if not path.is_dir():
        raise PretrainedFilesError(f"{what} {path} is not a directory (a local checkpoint is expected, e.g. a "
                                   "download of lerobot/pi05_base)")
    weights = path / WEIGHTS_FILE
    if not weights.is_file():
        raise PretrainedFilesError(f"{what} {path} has no {WEIGHTS_FILE}: refusing to use random weights "
                                   f"(found: {sorted(p.name for p in path.iterdir()) or 'nothing'})")
    return weights


def tokenizer_dir(path: str | Path | None) -> Path:
    """The local tokenizer directory `path`, checked to load offline; raises with what is missing."""
    if not path:
        raise PretrainedFilesError("policy.tokenizer_path is not set: pi05 needs a local PaliGemma tokenizer")
    path = Path(path)
    if not path.is_dir() or not any((path / f).is_file() for f in TOKENIZER_FILES):
        raise PretrainedFilesError(f"policy.tokenizer_path {path} is not a tokenizer directory (expected one of "
                                   f"{TOKENIZER_FILES}; e.g. save google/paligemma-3b-pt-224's tokenizer there)")
    from transformers import AutoTokenizer

    try:
        AutoTokenizer.from_pretrained(str(path), local_files_only=True)
    except (OSError, ValueError) as err:
        raise PretrainedFilesError(f"policy.tokenizer_path {path}: cannot load the tokenizer offline: {err}") from err
    return path


def check_weights_loaded(policy: torch.nn.Module, weights: Path) -> int:
    """Raise unless the policy holds the checkpoint's tensors; returns how many matching keys it compared.

    Compares up to WEIGHT_SAMPLES tensors spread over the checkpoint's keys that the policy also has
    (lerobot prefixes checkpoint keys with `model.`), in the policy's dtype.
    """
    from safetensors import safe_open

    state = policy.state_dict()
    with safe_open(str(weights), framework="pt") as f:
        pairs = [(k, k if k in state else f"model.{k}") for k in sorted(f.keys())]
        pairs = [(k, name) for k, name in pairs if name in state]
        if not pairs:
            raise PretrainedFilesError(f"{weights}: none of its tensors match the policy's parameter names")
        stride = max(1, len(pairs) // WEIGHT_SAMPLES)
        for key, name in pairs[::stride]:
            ours = state[name]
            theirs = f.get_tensor(key)
            if theirs.shape != ours.shape or not torch.equal(theirs.to(ours.dtype), ours.detach().cpu()):
                raise PretrainedFilesError(f"{weights}: tensor {key} was not loaded into the policy (shape "
                                           f"{tuple(theirs.shape)} vs {tuple(ours.shape)}); the checkpoint does "
                                           "not match policy.config (variant, dims) and lerobot fell back to "
                                           "random weights")
    return len(pairs[::stride])
