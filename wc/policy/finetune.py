"""Fine-tune one lerobot policy on one local LeRobot dataset and save it the lerobot way.

lerobot does the work: the policy config class and `make_policy` (loading `pretrained_path`),
the processors (wc.policy.processors), `LeRobotDataset` with the action chunk from
`resolve_delta_timestamps`, `EpisodeAwareSampler`, `AdamWConfig` and
`CosineDecayWithWarmupSchedulerConfig`. The loop around `policy.forward(batch)` is lerobot-train's
`update_policy` without accelerate. The output directory holds `config.json`, `model.safetensors`,
the two processor pipelines (plus the tokenizer for pi0.5) and `train_summary.json`, so
`load_policy` (or lerobot's own loaders) reads it back.
"""

from __future__ import annotations

import dataclasses
import json
import os
import secrets
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.configs import FeatureType, NormalizationMode, PreTrainedConfig
from lerobot.datasets import EpisodeAwareSampler, LeRobotDataset, LeRobotDatasetMetadata
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.optim import AdamWConfig, CosineDecayWithWarmupSchedulerConfig
from lerobot.policies import PreTrainedPolicy, make_policy
from lerobot.policies.factory import get_policy_class
from lerobot.processor import PolicyProcessorPipeline
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE
from lerobot.utils.feature_utils import dataset_to_policy_features
from lerobot.utils.random_utils import set_seed
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LRScheduler
from tqdm import tqdm

from wc.policy.policy_config import PolicyConfig
from wc.reports import replace_dir
from wc.policy.pretrained import checkpoint_weights, check_weights_loaded, tokenizer_dir
from wc.policy.processors import load_processors, make_processors

SUMMARY_FILE = "train_summary.json"
TOKENIZER_DIR = "tokenizer"


def dataset_metadata(root: str | Path, cfg: PolicyConfig) -> LeRobotDatasetMetadata:
    """Metadata of the local LeRobot dataset at `root`, checked to hold what `cfg` trains on."""
    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"finetune: no LeRobot dataset at {root} (run the dataset stage first)")
    meta = LeRobotDatasetMetadata(f"local/{root.name}", root=root)
    needed = [camera_feature(c) for c in cfg.cameras] + [OBS_STATE, ACTION]
    missing = [k for k in needed if k not in meta.features]
    if missing:
        raise ValueError(f"finetune: dataset {root} lacks feature {missing[0]} (has {sorted(meta.features)})")
    tasks = sorted(meta.tasks.index) if meta.tasks is not None else []
    if tasks != [cfg.task]:
        raise ValueError(f"finetune: dataset {root} has tasks {tasks}, expected only policy.task {cfg.task!r}")
    if meta.total_frames < cfg.batch_size:
        raise ValueError(f"finetune: dataset {root} has {meta.total_frames} frames, fewer than policy.batch_size "
                         f"{cfg.batch_size}")
    return meta


def camera_feature(camera: str) -> str:
    """The LeRobot feature key of a camera name, e.g. top -> observation.images.top."""
    return f"{OBS_IMAGES}.{camera}"


def policy_config(cfg: PolicyConfig, meta: LeRobotDatasetMetadata) -> PreTrainedConfig:
    """lerobot's config of `cfg.type` with the recipe of `cfg`, reading the dataset's cameras, state and action."""
    cls = PreTrainedConfig.get_choice_class(cfg.type)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(cfg.config) - set(fields))
    if unknown:
        raise ValueError(f"policy.config.{unknown[0]} is not a field of lerobot's {cls.__name__}")
    kwargs = {k: tuple(v) if isinstance(v, list) and isinstance(_default(fields[k]), tuple) else v
              for k, v in cfg.config.items()}
    recipe = {"optimizer_lr": cfg.lr, "optimizer_betas": tuple(cfg.betas), "optimizer_eps": cfg.eps,
              "optimizer_weight_decay": cfg.weight_decay, "optimizer_grad_clip_norm": cfg.grad_clip_norm,
              "scheduler_warmup_steps": cfg.warmup_steps, "scheduler_decay_steps": cfg.decay_steps,
              "scheduler_decay_lr": cfg.decay_lr}
    kwargs.update({k: v for k, v in recipe.items() if k in fields})  # recorded in config.json where it has a field
    kwargs.update(device=cfg.device, chunk_size=cfg.chunk_size, n_action_steps=cfg.n_action_steps, push_to_hub=False,
                  pretrained_path=Path(cfg.pretrained_path) if cfg.pretrained_path else None)
    if cfg.normalization:
        mapping = dict(_default(fields["normalization_mapping"]))
        mapping.update({k: NormalizationMode(v) for k, v in cfg.normalization.items()})
        kwargs["normalization_mapping"] = mapping
    config = cls(**kwargs)
    features = dataset_to_policy_features(meta.features)
    inputs = [camera_feature(c) for c in cfg.cameras] + [OBS_STATE]
    config.input_features = {k: features[k] for k in inputs}
    config.output_features = {ACTION: features[ACTION]}
    if any(features[camera_feature(c)].type is not FeatureType.VISUAL for c in cfg.cameras):
        raise ValueError(f"finetune: policy.cameras {list(cfg.cameras)} must all be image or video features")
    return config


def _default(field: dataclasses.Field) -> Any:
    return field.default_factory() if field.default_factory is not dataclasses.MISSING else field.default


def make_optimizer(cfg: PolicyConfig, policy: PreTrainedPolicy) -> tuple[Optimizer, LRScheduler]:
    """AdamW over the policy's own parameter groups and lerobot's cosine decay with linear warm-up."""
    optimizer = AdamWConfig(lr=cfg.lr, betas=tuple(cfg.betas), eps=cfg.eps, weight_decay=cfg.weight_decay,
                            grad_clip_norm=cfg.grad_clip_norm).build(policy.get_optim_params())
    schedule = CosineDecayWithWarmupSchedulerConfig(num_warmup_steps=cfg.warmup_steps, num_decay_steps=cfg.decay_steps,
                                                    peak_lr=cfg.lr, decay_lr=cfg.decay_lr)
    return optimizer, schedule.build(optimizer, cfg.steps)


def train_step(policy: PreTrainedPolicy, batch: dict[str, Any], optimizer: Optimizer, scheduler: LRScheduler | None,
               grad_clip_norm: float) -> float:
    """One update on a preprocessed batch: forward, backward, clip, step; returns the loss."""
    policy.train()
    loss, _ = policy.forward(batch)
    if not torch.isfinite(loss):
        raise FloatingPointError(f"finetune: non-finite training loss {loss.item()}")
    loss.backward()
    if grad_clip_norm > 0:
        torch.nn.utils.clip_grad_norm_(policy.parameters(), grad_clip_norm)
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    if scheduler is not None:
        scheduler.step()
    return loss.item()


def batches(dataset: LeRobotDataset, meta: LeRobotDatasetMetadata, cfg: PolicyConfig) -> Iterator[dict[str, Any]]:
    """Endless batches in a seeded, per-epoch shuffled order (a pure function of policy.seed)."""
    sampler = EpisodeAwareSampler(meta.episodes["dataset_from_index"], meta.episodes["dataset_to_index"],
                                  shuffle=True, seed=cfg.seed)
    loader = torch.utils.data.DataLoader(dataset, batch_size=cfg.batch_size, sampler=sampler, drop_last=True,
                                         num_workers=cfg.num_workers, persistent_workers=cfg.num_workers > 0,
                                         pin_memory=cfg.device.startswith("cuda"))
    while True:
        yield from loader  # each pass draws the sampler's next epoch


@dataclasses.dataclass
class Trainer:
    """A policy ready to train on one dataset, with its processors and optimiser."""

    cfg: PolicyConfig
    meta: LeRobotDatasetMetadata
    dataset: LeRobotDataset
    policy: PreTrainedPolicy
    preprocessor: PolicyProcessorPipeline
    postprocessor: PolicyProcessorPipeline
    optimizer: Optimizer
    scheduler: LRScheduler
    tokenizer: Path | None


def build_trainer(root: str | Path, cfg: PolicyConfig) -> Trainer:
    """Check the local files, seed, and build the dataset, policy, processors and optimiser for `root`."""
    meta = dataset_metadata(root, cfg)
    weights = checkpoint_weights(cfg.pretrained_path) if cfg.pretrained_path else None
    tokenizer = tokenizer_dir(cfg.tokenizer_path) if cfg.type == "pi05" else None
    config = policy_config(cfg, meta)
    set_seed(cfg.seed)
    dataset = LeRobotDataset(meta.repo_id, root=root, delta_timestamps=resolve_delta_timestamps(config, meta),
                             video_backend=cfg.video_backend)
    policy = make_policy(config, ds_meta=meta)
    if weights is not None:
        check_weights_loaded(policy, weights)
    preprocessor, postprocessor = make_processors(config, meta.stats, tokenizer)
    optimizer, scheduler = make_optimizer(cfg, policy)
    return Trainer(cfg, meta, dataset, policy, preprocessor, postprocessor, optimizer, scheduler, tokenizer)


def finetune(root: str | Path, out: str | Path, cfg: PolicyConfig, meta: dict[str, Any] | None = None,
             progress: bool = True) -> dict[str, Any]:
    """Train `cfg.steps` steps on the dataset at `root` and save the policy at `out` (atomically).

    Returns the summary also written to `<out>/train_summary.json`: losses every
    `log_every_steps`, the final loss (mean of the last log window), timings and `meta`.
    """
    start = time.perf_counter()
    trainer = build_trainer(root, cfg)
    history, window, step_s = [], [], []
    data = batches(trainer.dataset, trainer.meta, cfg)
    bar = tqdm(range(1, cfg.steps + 1), desc=f"finetune {Path(root).name}", disable=not progress, unit="step")
    for step in bar:
        t0 = time.perf_counter()
        loss = train_step(trainer.policy, trainer.preprocessor(next(data)), trainer.optimizer, trainer.scheduler,
                          cfg.grad_clip_norm)
        step_s.append(time.perf_counter() - t0)
        window.append(loss)
        if step % cfg.log_every_steps == 0 or step == cfg.steps:
            history.append({"step": step, "loss": float(np.mean(window)), "lr": trainer.scheduler.get_last_lr()[0]})
            window = []
            bar.set_postfix(loss=f"{history[-1]['loss']:.4g}")
    summary = {"dataset": str(root), "policy_type": cfg.type, "steps": cfg.steps, "batch_size": cfg.batch_size,
               "seed": cfg.seed, "episodes": trainer.meta.total_episodes, "frames": trainer.meta.total_frames,
               "first_loss": history[0]["loss"], "final_loss": history[-1]["loss"], "history": history,
               "s_per_step_median": float(np.median(step_s)), "train_s": float(np.sum(step_s)),
               "parameters": sum(p.numel() for p in trainer.policy.parameters()),
               "pretrained_path": cfg.pretrained_path, **(meta or {})}
    save_policy(trainer, Path(out), summary)
    summary["wall_s"] = time.perf_counter() - start
    return summary


def save_policy(trainer: Trainer, out: Path, summary: dict[str, Any]) -> None:
    """Policy, processors, tokenizer (pi0.5) and summary into a temporary sibling, then renamed to `out`."""
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        trainer.policy.save_pretrained(tmp)
        trainer.preprocessor.save_pretrained(tmp)
        trainer.postprocessor.save_pretrained(tmp)
        if trainer.tokenizer is not None:
            shutil.copytree(trainer.tokenizer, tmp / TOKENIZER_DIR)
        (tmp / SUMMARY_FILE).write_text(json.dumps(summary, indent=2, default=str) + "\n")
        _replace_dir(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _replace_dir(tmp: Path, path: Path) -> None:
    """Rename the finished `tmp` to `path`, replacing only a previously saved policy (or an empty directory)."""
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise FileExistsError(f"{path} exists and is not a directory; refusing to replace it")
    if path.is_dir() and any(path.iterdir()) and not (path / SUMMARY_FILE).is_file():
        raise FileExistsError(f"{path} is a non-empty directory that is not a saved policy; refusing to replace it")
    replace_dir(tmp, path)


def load_policy(path: str | Path, device: str = "cpu", tokenizer: str | Path | None = None
                ) -> tuple[PreTrainedPolicy, PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """(policy in eval mode, preprocessor, postprocessor) saved by `finetune` at `path`, on `device`."""
    path = Path(path)
    weights = checkpoint_weights(path, "saved policy")
    config = PreTrainedConfig.from_pretrained(path)
    config.device = device
    policy = get_policy_class(config.type).from_pretrained(path, config=config)
    check_weights_loaded(policy, weights)
    policy.to(device).eval()
    preprocessor, postprocessor = load_processors(path, config, device, tokenizer)
    return policy, preprocessor, postprocessor
