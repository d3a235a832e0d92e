"""lerobot 0.6.1's own trainer, `lerobot.scripts.lerobot_train.train` (what `lerobot-train` runs), for one
`PolicyConfig`.

- `train_config`: the `TrainPipelineConfig` the stage hands to `train`: the local dataset directory, the
  policy config (wc.policy.finetune.policy_config), steps, batch size, seed, workers and log cadence; AdamW
  and cosine decay with warm-up from the params (not the policy preset: ACT's has a constant learning rate);
  the dataset's own image stats (no ImageNet stats); wandb, Hub pushes and env evaluation off; lerobot's
  checkpoints (every `save_freq` steps and after the last) under `output_dir`.
- `starting_checkpoint`: with a pretrained path, `train` loads the weights *and the processors* from that
  directory; this writes one holding our processors (wc.policy.processors: pi0.5's tokenizer from a local
  directory, where lerobot 0.6.1 would go to the Hub) beside a link to the checkpoint's weights.
- `StepRecorder`: `train` accepts an Accelerator; ours takes lerobot's own arguments and records the loss
  handed to every `backward` (the exact loss lerobot optimises, every step: no log parsing, no patching of
  lerobot) with the learning rate and the time between updates; when `train` hands it the policy
  (`prepare`), it checks the pretrained tensors were loaded (lerobot falls back to random weights with a print).
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from accelerate import Accelerator
from accelerate.utils import DistributedDataParallelKwargs
from lerobot.configs import PreTrainedConfig
from lerobot.configs.default import DatasetConfig, WandBConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.optim import AdamWConfig, CosineDecayWithWarmupSchedulerConfig
from lerobot.policies import PreTrainedPolicy
from lerobot.scripts import lerobot_train
from lerobot.utils.constants import CHECKPOINTS_DIR, LAST_CHECKPOINT_LINK, PRETRAINED_MODEL_DIR
from torch.optim import Optimizer

from wc.policy.policy_config import PolicyConfig
from wc.policy.pretrained import WEIGHTS_FILE, check_weights_loaded
from wc.policy.processors import Stats, make_processors

REPO_OWNER = "worldcontact"  # dataset.repo_id = worldcontact/<dataset dir name>; a label, the data is local


def train_config(root: Path, cfg: PolicyConfig, policy: PreTrainedConfig, output_dir: Path) -> TrainPipelineConfig:
    """lerobot-train's config: train `policy` on the local dataset at `root` with the recipe of `cfg`."""
    return TrainPipelineConfig(
        dataset=DatasetConfig(repo_id=f"{REPO_OWNER}/{root.name}", root=str(root), video_backend=cfg.video_backend,
                              use_imagenet_stats=False),
        policy=policy, output_dir=output_dir, job_name=f"{cfg.type}_{root.name}", seed=cfg.seed,
        num_workers=cfg.num_workers, batch_size=cfg.batch_size, steps=cfg.steps, log_freq=cfg.log_every_steps,
        save_checkpoint=True, use_policy_training_preset=False,
        optimizer=AdamWConfig(lr=cfg.lr, betas=tuple(cfg.betas), eps=cfg.eps, weight_decay=cfg.weight_decay,
                              grad_clip_norm=cfg.grad_clip_norm),
        scheduler=CosineDecayWithWarmupSchedulerConfig(num_warmup_steps=cfg.warmup_steps,
                                                       num_decay_steps=cfg.decay_steps, peak_lr=cfg.lr,
                                                       decay_lr=cfg.decay_lr),
        env=None, eval_steps=0, wandb=WandBConfig(enable=False))


def starting_checkpoint(path: Path, config: PreTrainedConfig, stats: Stats, weights: Path,
                        tokenizer: Path | None) -> Path:
    """A directory `train` starts from: a link to the pretrained `weights` and new processors for the dataset."""
    path.mkdir()
    (path / WEIGHTS_FILE).symlink_to(weights.resolve())
    for pipeline in make_processors(config, stats, tokenizer):
        pipeline.save_pretrained(path)
    return path


def last_checkpoint(output_dir: Path) -> Path:
    """The `pretrained_model` directory (policy, config, processors) of lerobot's last checkpoint."""
    path = (output_dir / CHECKPOINTS_DIR / LAST_CHECKPOINT_LINK).resolve() / PRETRAINED_MODEL_DIR
    if not (path / WEIGHTS_FILE).is_file():
        raise FileNotFoundError(f"finetune: lerobot-train left no final checkpoint at {path}")
    return path


class StepRecorder(Accelerator):
    """lerobot-train's Accelerator, also recording each update's loss, learning rate and duration."""

    def __init__(self, weights: Path | None = None, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.weights = weights  # pretrained checkpoint the policy must hold when training starts
        self.losses: list[float] = []
        self.lrs: list[float] = []  # learning rate of each update
        self.step_s: list[float] = []  # time between consecutive updates (data, preprocessing, forward to step)
        self.parameters = 0
        self._optimizer: Optimizer | None = None
        self._tick = 0.0

    def prepare(self, *args: Any, device_placement: list[bool] | None = None) -> Any:
        policy = next((a for a in args if isinstance(a, PreTrainedPolicy)), None)
        if policy is not None:
            if self.weights is not None:
                check_weights_loaded(policy, self.weights)
            self.parameters = sum(p.numel() for p in policy.parameters())
        self._optimizer = next((a for a in args if isinstance(a, Optimizer)), self._optimizer)
        prepared = super().prepare(*args, device_placement=device_placement)
        self._tick = time.perf_counter()
        return prepared

    def backward(self, loss: torch.Tensor, **kwargs: Any) -> None:
        value = loss.item()
        if not math.isfinite(value):
            raise FloatingPointError(f"finetune: non-finite training loss {value} at step {len(self.losses) + 1}")
        super().backward(loss, **kwargs)
        now = time.perf_counter()
        self.losses.append(value)
        self.lrs.append(self._optimizer.param_groups[0]["lr"] if self._optimizer is not None else math.nan)
        self.step_s.append(now - self._tick)
        self._tick = now


def make_accelerator(config: PreTrainedConfig, weights: Path | None = None) -> StepRecorder:
    """A StepRecorder with the arguments lerobot 0.6.1's `train` gives its own Accelerator for `config`."""
    mixed_precision = {"bfloat16": "bf16", "float16": "fp16", "float32": "no"}.get(getattr(config, "dtype", None))
    if not hasattr(config, "dtype") and config.use_amp:
        dtype = torch.get_autocast_dtype(torch.device(config.device).type)
        mixed_precision = {torch.bfloat16: "bf16", torch.float16: "fp16"}[dtype]
    accelerator = StepRecorder(weights, step_scheduler_with_optimizer=False, mixed_precision=mixed_precision,
                               kwargs_handlers=[DistributedDataParallelKwargs(find_unused_parameters=True)],
                               cpu=config.device == "cpu")
    if accelerator.num_processes > 1:
        raise RuntimeError("finetune: the stage trains in one process (one GPU or the CPU); for several GPUs run "
                           "`accelerate launch --multi_gpu $(which lerobot-train) ...` per dataset")
    return accelerator


def train(train_cfg: TrainPipelineConfig, accelerator: StepRecorder) -> None:
    """lerobot's `train(train_cfg)`, with our accelerator, deaf to this process's own command line."""
    with _without_cli_args():
        lerobot_train.train(train_cfg, accelerator=accelerator)


@contextlib.contextmanager
def _without_cli_args() -> Iterator[None]:
    """`TrainPipelineConfig.validate` reads `--policy.path` / `--config_path` from sys.argv; ours are not for it."""
    argv = sys.argv
    sys.argv = argv[:1]
    try:
        yield
    finally:
        sys.argv = argv
