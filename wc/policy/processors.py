"""lerobot pre-/post-processor pipelines for a policy config, built offline.

ACT (and any policy whose factory needs no download) goes through lerobot's
`make_pre_post_processors`. lerobot 0.6.1's pi0.5 factory hard-codes the Hub tokenizer
`google/paligemma-3b-pt-224` (configurable only upstream, after 0.6.1), so `make_pi05_processors`
assembles the same steps in the same order with the tokenizer read from a local directory;
tests/test_finetune.py checks it against lerobot's factory step by step.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from lerobot.configs import PreTrainedConfig
from lerobot.policies import make_pre_post_processors
from lerobot.processor import (
    AbsoluteActionsProcessorStep,
    PolicyProcessorPipeline,
    RelativeActionsProcessorStep,
    TokenizerProcessorStep,
    make_default_policy_processor_steps,
    make_policy_processor_pipelines,
)

Stats = dict[str, dict[str, torch.Tensor]]
TOKENIZER_STEP = "tokenizer_processor"  # registry name of lerobot's TokenizerProcessorStep


def make_processors(config: PreTrainedConfig, stats: Stats,
                    tokenizer: str | Path | None = None) -> tuple[PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """(preprocessor, postprocessor) for a new policy, normalising with the dataset `stats`."""
    if config.type == "pi05":
        if tokenizer is None:
            raise ValueError("pi05 needs a local tokenizer directory")
        return make_pi05_processors(config, stats, tokenizer)
    return make_pre_post_processors(config, dataset_stats=stats)


def make_pi05_processors(config: Any, stats: Stats,
                         tokenizer: str | Path) -> tuple[PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """lerobot's `make_pi05_pre_post_processors` (0.6.1) with the tokenizer loaded from `tokenizer`."""
    from lerobot.policies.pi05.processor_pi05 import Pi05PrepareStateTokenizerProcessorStep

    relative = RelativeActionsProcessorStep(enabled=config.use_relative_actions,
                                            exclude_joints=getattr(config, "relative_exclude_joints", []),
                                            action_names=getattr(config, "action_feature_names", None))
    steps = make_default_policy_processor_steps(config, stats)
    input_steps = [
        steps.rename_observations,
        steps.add_batch_dim,
        relative,
        steps.normalize,  # before the state tokenizer: it bins the state normalised to [-1, 1]
        Pi05PrepareStateTokenizerProcessorStep(max_state_dim=config.max_state_dim),
        TokenizerProcessorStep(tokenizer_name=str(tokenizer), max_length=config.tokenizer_max_length,
                               padding_side="right", padding="max_length"),
        steps.to_device,
    ]
    output_steps = [
        steps.unnormalize,
        AbsoluteActionsProcessorStep(enabled=config.use_relative_actions, relative_step=relative),
        steps.to_cpu,
    ]
    return make_policy_processor_pipelines(input_steps=input_steps, output_steps=output_steps)


def load_processors(path: str | Path, config: PreTrainedConfig, device: str,
                    tokenizer: str | Path | None = None) -> tuple[PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """The processors saved beside a policy at `path`, through lerobot's loader, on `device`.

    pi0.5: the tokenizer is read from `tokenizer`, else from `<path>/tokenizer` when the policy was
    saved with one (wc.policy.finetune saves it there), else from where it was read in training.
    """
    overrides: dict[str, Any] = {"device_processor": {"device": device}}
    if config.type == "pi05":
        local = Path(tokenizer) if tokenizer else Path(path) / "tokenizer"
        if local.is_dir():
            overrides[TOKENIZER_STEP] = {"tokenizer_name": str(local)}
    return make_pre_post_processors(config, pretrained_path=str(path), preprocessor_overrides=overrides)
