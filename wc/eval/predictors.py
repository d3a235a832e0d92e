"""The learned predictors `evaluate` compares (and expand rolls out), behind one tiny tensor interface.

A `Predictor` advances the object state of one scene layout under prescribed body poses:

    x, v = predictor.rollout(layout, x0, v0, poses, dt)
    layout: wc.model.layout.SceneLayout (objects, rest topology, prescribed sample sets)
    x0, v0: (B, N, 3) torch tensors, m and m/s;  poses: (B, T, P, 7) body poses of frames 0..T-1
    returns x, v: (B, T-1, N, 3), frames 1..T-1 (non-finite values are allowed: a diverged rollout)

A predictor that reads past frames beyond the current state says how many in `history` (the particle baselines'
n_his; default 1). The baselines (wc.baselines.load_baseline(path)) follow the same shape. Implemented here: zero
motion, constant velocity and WorldContact from a checkpoint directory. Every one of them is rolled out as
`wc.dynamics.Dynamics` through wc.model.learned_dynamics.LearnedDynamics (evaluate: wc.eval.methods).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from wc.eval.config import WORLDCONTACT_KEYS, MethodSpec
from wc.model.layout import SceneLayout
from wc.model.predictor import Predictor, WorldContactPredictor, rollout_steps
from wc.model_ref import is_hub_ref, resolve_model_dir
from wc.train.config import TrainConfig

class ZeroMotion:
    """Reference: every vertex stays where it is, v = 0."""

    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        steps = rollout_steps(x0, poses)
        x = x0[:, None].expand(-1, steps, -1, -1)
        return x.clone(), torch.zeros_like(x)


class ConstantVelocity:
    """Reference: every vertex keeps its initial velocity, x_k = x0 + k·v0·dt, v_k = v0."""

    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        steps = rollout_steps(x0, poses)
        k = torch.arange(1, steps + 1, dtype=x0.dtype, device=x0.device)[None, :, None, None]
        return x0[:, None] + k * dt * v0[:, None], v0[:, None].expand(-1, steps, -1, -1).clone()


def load_predictor(spec: MethodSpec, train_cfg: TrainConfig, device: torch.device) -> Predictor:
    """The learned predictor or reference a params method entry names (not kind newton: wc.eval.methods).
    FileNotFoundError when its checkpoint directory is absent (the stage skips such methods with a note);
    ImportError when no baseline package is installed."""
    if spec.kind == "newton":
        raise ValueError("a method of kind 'newton' is the simulator, not a predictor: wc.eval.methods.load_method")
    if spec.kind == "zero_motion":
        return ZeroMotion()
    if spec.kind == "constant_velocity":
        return ConstantVelocity()
    if not is_hub_ref(spec.path) and not Path(spec.path).is_dir():
        raise FileNotFoundError(f"checkpoint directory {spec.path} not found")
    path = resolve_model_dir(spec.path, "evaluate.methods path")  # hf://owner/repo[/folder]: downloaded
    if spec.kind == "worldcontact":
        overrides = {key: getattr(spec, key) for key in WORLDCONTACT_KEYS if getattr(spec, key) is not None}
        train_cfg = dataclasses.replace(train_cfg, **overrides)
        return WorldContactPredictor.from_dir(path, train_cfg, device)
    from wc.baselines import load_baseline  # noqa: PLC0415 - written separately; optional until it lands

    return load_baseline(path, device)
