"""Fine-tune one lerobot policy on one local LeRobot dataset with lerobot's own trainer, and save it.

Both policy types (ACT, the CPU default, and pi0.5) train through lerobot 0.6.1's
`lerobot.scripts.lerobot_train.train` (what `lerobot-train` runs; wc.policy.stock_trainer): dataset
loading, sampling, the update loop, accelerate (mixed precision), logging and checkpoints are lerobot's.
This module checks the local files first, builds lerobot's policy config from params `policy`
(`policy_config`), and afterwards moves lerobot's final `checkpoints/last/pretrained_model` (config.json,
model.safetensors, train_config.json and the two processor pipelines) into `out` atomically, adding the
tokenizer (pi0.5) and `train_summary.json`; `load_policy` (or lerobot's own loaders) reads it back.
pi0.5 starts from a local checkpoint whose processors read a local tokenizer (wc.policy.processors),
which lerobot 0.6.1 alone would fetch from the Hub.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import lerobot
import numpy as np
from huggingface_hub.constants import CONFIG_NAME
from lerobot.configs import FeatureType, NormalizationMode, PreTrainedConfig
from lerobot.datasets import LeRobotDatasetMetadata
from lerobot.policies import PreTrainedPolicy
from lerobot.policies.factory import get_policy_class
from lerobot.processor import PolicyProcessorPipeline
from lerobot.utils.constants import ACTION, CHECKPOINTS_DIR, OBS_IMAGES, OBS_STATE
from lerobot.utils.feature_utils import dataset_to_policy_features

from wc.atomic import remove_stale_temporaries, temporary_sibling
from wc.policy.comparison import SUMMARY_FILE
from wc.policy.policy_config import PolicyConfig
from wc.policy.pretrained import PretrainedFilesError, check_weights_loaded, checkpoint_weights, tokenizer_dir
from wc.policy.processors import load_processors
from wc.policy.stock_trainer import (StepRecorder, last_checkpoint, make_accelerator, starting_checkpoint, train,
                                    train_config)
from wc.reports import replace_dir

TOKENIZER_DIR = "tokenizer"


def dataset_metadata(root: str | Path, cfg: PolicyConfig) -> LeRobotDatasetMetadata:
    """Metadata of the local LeRobot dataset at `root`, checked to hold what `cfg` trains on."""
    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"finetune: no LeRobot dataset at {root} (run the dataset stage first)")
    try:
        meta = LeRobotDatasetMetadata(f"local/{root.name}", root=root)
    except json.JSONDecodeError as err:  # lerobot's message names no file
        raise ValueError(f"finetune: {invalid_json(root / 'meta', err)} (rebuild the dataset with the dataset "
                         "stage)") from err
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


def invalid_json(folder: Path, err: json.JSONDecodeError) -> str:
    """Which JSON file under `folder` does not parse, and where: '<file> is not valid JSON: <msg>: line L column C'
    (the first that fails; `err`, lerobot's error, when each parses on its own)."""
    for path in sorted(folder.rglob("*.json")):
        try:
            json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as bad:
            return f"{path} is not valid JSON: {bad}"
    return f"a JSON file under {folder} is not valid JSON: {err}"


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
              "scheduler_decay_lr": cfg.decay_lr, "optimizer_lr_backbone": cfg.lr}
    if cfg.config.get("optimizer_lr_backbone", cfg.lr) != cfg.lr:  # ACT: only its own preset has a backbone lr
        raise ValueError(f"policy.config.optimizer_lr_backbone ({cfg.config['optimizer_lr_backbone']}) must equal "
                         f"policy.lr ({cfg.lr}): lerobot-train with the params' optimiser trains every parameter "
                         "at one learning rate")
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


def finetune(root: str | Path, out: str | Path, cfg: PolicyConfig, meta: dict[str, Any] | None = None
             ) -> dict[str, Any]:
    """Train `cfg.steps` steps on the dataset at `root` with lerobot-train and save the policy at `out` (atomically).

    Returns the summary also written to `<out>/train_summary.json`: the mean loss of every `log_every_steps`
    window (and of the last, shorter one), the final loss (the last window's), timings and `meta`. Should
    training fail after lerobot saved a checkpoint, its run directory is kept (and named) for lerobot's resume.
    """
    start = time.perf_counter()
    root, out = Path(root), Path(out)
    ds_meta = dataset_metadata(root, cfg)
    weights = checkpoint_weights(cfg.pretrained_path) if cfg.pretrained_path else None
    tokenizer = tokenizer_dir(cfg.tokenizer_path) if cfg.type == "pi05" else None
    if tokenizer is not None and weights is None:
        raise PretrainedFilesError("policy.pretrained_path is not set: lerobot-train reads pi05's processors (and "
                                   "its local tokenizer) from the starting checkpoint; name a local one, e.g. "
                                   "pretrained/pi05_base")
    config = policy_config(cfg, ds_meta)
    _check_replaceable(out)  # before training, not after
    remove_stale_temporaries(out)
    scratch = temporary_sibling(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    scratch.mkdir()
    run_dir, keep = scratch / "lerobot_train", False
    try:
        if weights is not None:
            config.pretrained_path = starting_checkpoint(scratch / "start", config, ds_meta.stats, weights, tokenizer)
        recorder = make_accelerator(config, weights)
        train(train_config(root, cfg, config, run_dir), recorder)
        summary = {"dataset": str(root), "policy_type": cfg.type, "trainer": f"lerobot-train {lerobot.__version__}",
                   "steps": cfg.steps, "batch_size": cfg.batch_size, "seed": cfg.seed,
                   "episodes": ds_meta.total_episodes, "frames": ds_meta.total_frames, **run_summary(recorder, cfg),
                   "pretrained_path": cfg.pretrained_path, **(meta or {})}
        save_policy(last_checkpoint(run_dir), out, summary, tokenizer, cfg.pretrained_path)
    except BaseException:
        keep = (run_dir / CHECKPOINTS_DIR).is_dir()
        if keep:
            print(f"finetune: training {root} failed; lerobot's run directory {run_dir} is kept (resume: lerobot-train "
                  f"--config_path={run_dir}/{CHECKPOINTS_DIR}/last/pretrained_model/train_config.json --resume=true)",
                  file=sys.stderr, flush=True)
        raise
    finally:
        if not keep:
            shutil.rmtree(scratch, ignore_errors=True)
    summary["wall_s"] = time.perf_counter() - start
    return summary


def run_summary(recorder: StepRecorder, cfg: PolicyConfig) -> dict[str, Any]:
    """What the recorder saw of lerobot's updates: `history` (mean loss of each `log_every_steps` window, the last
    one possibly shorter, with the learning rate of its last update), first and final loss (the first and last
    windows'), the median and total time per update, and the policy's parameter count."""
    losses, every = recorder.losses, cfg.log_every_steps
    if not losses:
        raise RuntimeError("finetune: lerobot-train ran no training step")
    ends = [k for k in range(1, len(losses) + 1) if k % every == 0 or k == len(losses)]
    history = [{"step": k, "loss": float(np.mean(losses[max(0, k - every):k])), "lr": recorder.lrs[k - 1]}
               for k in ends]
    return {"first_loss": history[0]["loss"], "final_loss": history[-1]["loss"], "history": history,
            "s_per_step_median": float(np.median(recorder.step_s)), "train_s": float(np.sum(recorder.step_s)),
            "parameters": recorder.parameters}


def save_policy(model: Path, out: Path, summary: dict[str, Any], tokenizer: Path | None = None,
                pretrained_path: str | None = None) -> None:
    """lerobot's final `pretrained_model` directory (a temporary sibling of `out`), completed with the tokenizer
    (pi0.5) and the summary, renamed to `out`. config.json names the checkpoint training started from."""
    config_file = model / CONFIG_NAME
    config = json.loads(config_file.read_text())
    config["pretrained_path"] = pretrained_path  # not the temporary starting directory
    config_file.write_text(json.dumps(config, indent=4) + "\n")
    if tokenizer is not None:
        shutil.copytree(tokenizer, model / TOKENIZER_DIR)
    (model / SUMMARY_FILE).write_text(json.dumps(summary, indent=2, default=str) + "\n")
    _replace_dir(model, out)


def _replace_dir(tmp: Path, path: Path) -> None:
    """Rename the finished `tmp` to `path`, replacing only a previously saved policy (or an empty directory)."""
    _check_replaceable(path)
    replace_dir(tmp, path)


def _check_replaceable(path: Path) -> None:
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise FileExistsError(f"{path} exists and is not a directory; refusing to replace it")
    if path.is_dir() and any(path.iterdir()) and not (path / SUMMARY_FILE).is_file():
        raise FileExistsError(f"{path} is a non-empty directory that is not a saved policy; refusing to replace it")


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
