"""Params of the `finetune` stage (`policy:` in params.yaml): which LeRobot policy, its optimiser and
schedule, and the local files a pretrained pi0.5 needs.

The optimiser is always AdamW and the schedule lerobot's `cosine_decay_with_warmup` (linear warm-up
to `lr`, cosine decay to `decay_lr` at `decay_steps`; lerobot compresses both when `steps` is
shorter than `decay_steps`). Fields of lerobot's own policy config class that have no key here go
in `config` (e.g. ACT's `dim_model`, pi0.5's `dtype`); the keys set from this section may not.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from wc.devices import check_device_name

POLICY_TYPES = ("act", "pi05")
NORMALIZATION_MODES = ("IDENTITY", "MEAN_STD", "MIN_MAX", "QUANTILES", "QUANTILE10")
FEATURE_TYPES = ("VISUAL", "STATE", "ACTION")
# lerobot config fields this section sets itself: they may not appear again in `config`
RESERVED_CONFIG_KEYS = ("device", "chunk_size", "n_action_steps", "pretrained_path", "normalization_mapping",
                        "input_features", "output_features", "push_to_hub", "optimizer_lr", "optimizer_betas",
                        "optimizer_eps", "optimizer_weight_decay", "optimizer_grad_clip_norm",
                        "scheduler_warmup_steps", "scheduler_decay_steps", "scheduler_decay_lr")


@dataclass(frozen=True)
class PolicyConfig:
    type: Literal["act", "pi05"]  # lerobot policy type
    datasets: tuple[str, ...]  # data/lerobot/<name> to train on, one policy each, identical settings and seed
    task: str  # instruction every training frame must carry, e.g. "right grasp and lift"
    cameras: tuple[str, ...]  # image inputs observation.images.<camera>, e.g. [top, wrist]
    steps: int  # optimiser steps per policy
    batch_size: int
    lr: float  # peak learning rate (after warm-up)
    betas: tuple[float, float]  # AdamW
    eps: float
    weight_decay: float
    grad_clip_norm: float  # max global gradient norm (0: off)
    warmup_steps: int
    decay_steps: int  # cosine decay from lr to decay_lr over this many steps
    decay_lr: float
    chunk_size: int  # actions predicted per inference
    n_action_steps: int  # of which this many are executed
    device: str  # cpu | cuda | cuda:k
    seed: int
    num_workers: int = 0  # DataLoader worker processes
    side_by_side: bool = False  # train every dataset's policy at once, each in its own process (one device shared)
    log_every_steps: int = 10  # training loss recorded every k steps (and on the last)
    video_backend: str = "pyav"  # lerobot video decoder
    pretrained_path: str | None = None  # local checkpoint dir with model.safetensors (pi0.5: e.g. pi05_base)
    tokenizer_path: str | None = None  # pi0.5: local PaliGemma tokenizer dir (lerobot's default is a Hub download)
    normalization: dict[str, str] | None = None  # VISUAL/STATE/ACTION -> mode; None: the policy's default
    config: dict[str, Any] = field(default_factory=dict)  # further fields of lerobot's <Type>Config

    def validate(self) -> None:
        if self.type not in POLICY_TYPES:
            raise ValueError(f"policy.type must be one of {POLICY_TYPES}, got {self.type!r}")
        if not self.datasets or len(set(self.datasets)) != len(self.datasets):
            raise ValueError(f"policy.datasets must be distinct dataset names, got {list(self.datasets)}")
        if not self.task.strip():
            raise ValueError("policy.task must be a non-empty instruction")
        if not self.cameras or len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"policy.cameras must be distinct camera names, got {list(self.cameras)}")
        for name in ("steps", "batch_size", "chunk_size", "n_action_steps", "decay_steps", "log_every_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"policy.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("warmup_steps", "num_workers", "seed"):
            if getattr(self, name) < 0:
                raise ValueError(f"policy.{name} must be >= 0, got {getattr(self, name)}")
        if self.warmup_steps >= self.decay_steps:
            raise ValueError(f"policy.warmup_steps ({self.warmup_steps}) must be below decay_steps ({self.decay_steps})")
        if not self.lr > 0 or not 0 <= self.decay_lr <= self.lr:
            raise ValueError(f"policy.lr must be > 0 and policy.decay_lr in [0, lr], got {self.lr}, {self.decay_lr}")
        if not all(0 <= b < 1 for b in self.betas) or not self.eps > 0:
            raise ValueError(f"policy.betas must be in [0, 1) and eps > 0, got {self.betas}, {self.eps}")
        if self.weight_decay < 0 or self.grad_clip_norm < 0:
            raise ValueError("policy.weight_decay and policy.grad_clip_norm must be >= 0")
        if self.n_action_steps > self.chunk_size:
            raise ValueError(f"policy.n_action_steps ({self.n_action_steps}) exceeds chunk_size ({self.chunk_size})")
        check_device_name(self.device, "policy.device", allow_auto=False)
        if self.type == "pi05" and not self.tokenizer_path:
            raise ValueError("policy.tokenizer_path must name a local PaliGemma tokenizer directory for pi05")
        for key, mode in (self.normalization or {}).items():
            if key not in FEATURE_TYPES or mode not in NORMALIZATION_MODES:
                raise ValueError(f"policy.normalization.{key}: keys must be in {FEATURE_TYPES} and modes in "
                                 f"{NORMALIZATION_MODES}, got {mode!r}")
        reserved = sorted(set(self.config) & set(RESERVED_CONFIG_KEYS))
        if reserved:
            raise ValueError(f"policy.config.{reserved[0]} is set by this section itself; remove it from config")
