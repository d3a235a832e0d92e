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
from contextlib import nullcontext
from pathlib import Path
from typing import Protocol

import torch

from wc.eval.config import WORLDCONTACT_KEYS, MethodSpec
from wc.model.layout import SceneLayout
from wc.model.fixed_neighbors import capacities_from_dict
from wc.model.padded_neighbors import NeighborCapacity
from wc.model.rollout import rollout
from wc.model.static_rollout import StaticRollout
from wc.model.worldcontact import WorldContact
from wc.model_ref import WEIGHTS, is_hub_ref, resolve_model_dir
from wc.train.capacity import initial_capacities
from wc.train.checkpoint import load_model
from wc.train.config import TrainConfig

CHECKPOINT = WEIGHTS  # a saved model folder's weights file


class Predictor(Protocol):
    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicted x, v (B, T-1, N, 3) for frames 1..T-1 from x0, v0 (B, N, 3) under poses (B, T, P, 7)."""
        ...


def _steps(x0: torch.Tensor, poses: torch.Tensor) -> int:
    if x0.ndim != 3 or poses.ndim != 4 or poses.shape[0] != x0.shape[0] or poses.shape[1] < 2:
        raise ValueError(f"x0 must be (B, N, 3) and poses (B, T>=2, P, 7), got {tuple(x0.shape)} and "
                         f"{tuple(poses.shape)}")
    return poses.shape[1] - 1


class ZeroMotion:
    """Reference: every vertex stays where it is, v = 0."""

    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        steps = _steps(x0, poses)
        x = x0[:, None].expand(-1, steps, -1, -1)
        return x.clone(), torch.zeros_like(x)


class ConstantVelocity:
    """Reference: every vertex keeps its initial velocity, x_k = x0 + k·v0·dt, v_k = v0."""

    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        steps = _steps(x0, poses)
        k = torch.arange(1, steps + 1, dtype=x0.dtype, device=x0.device)[None, :, None, None]
        return x0[:, None] + k * dt * v0[:, None], v0[:, None].expand(-1, steps, -1, -1).clone()


class WorldContactPredictor:
    """WorldContact (eval mode), with its topology projection when the checkpoint was trained with it.

    Steps one frame at a time so that a rollout that turns non-finite stops there (the model refuses
    non-finite inputs) and the remaining frames are NaN. With `train.static` the frames run on the static-shape
    path (`StaticRollout`: fixed-K neighbours with the checkpoint's capacities, CUDA-graphed on CUDA).
    """

    def __init__(self, model: WorldContact, projection: bool, train_cfg: TrainConfig,
                 capacities: dict[str, NeighborCapacity] | None = None) -> None:
        self.model = model.eval()
        self.projection = projection
        self.train_cfg = train_cfg
        self.capacities = capacities
        self._static: StaticRollout | None = None

    @classmethod
    def from_dir(cls, path: str | Path, train_cfg: TrainConfig, device: torch.device) -> WorldContactPredictor:
        """Load <path>/model.safetensors + model.json; the json's "projection" says whether P is applied, its
        "capacities" the static neighbour capacities measured in training (if it was trained on that path)."""
        model, config = load_model(path, device)  # a model folder or hf://owner/repo[/folder] (wc/model_ref.py)
        capacities = capacities_from_dict(config["capacities"]) if config.get("capacities") else None
        return cls(model, bool(config.get("projection", False)), train_cfg, capacities)

    @property
    def tag_scale(self) -> float:
        return float(self.model.config.tag_scale)

    def _projector(self, layout: SceneLayout):  # noqa: ANN202 - TopologyProjection | None
        if not self.projection:
            return None
        c = self.train_cfg
        return self.model.projection(layout, c.smoothing_iterations, c.smoothing_weight, c.constraint_iterations,
                                     c.edge_ratio)

    def _static_rollout(self, layout: SceneLayout, x0: torch.Tensor, poses: torch.Tensor, dt: float) -> StaticRollout:
        if self._static is None or self._static.dt != dt:
            c = self.train_cfg
            capacities = self.capacities or initial_capacities(self.model.config, layout, x0, poses, dt)
            self._static = StaticRollout(self.model, capacities, dt, compile=c.compile, cuda_graph=c.cuda_graph,
                                         autocast_bf16=c.autocast_bf16)
        return self._static

    @torch.no_grad()
    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        steps = _steps(x0, poses)
        projection = self._projector(layout)
        if self.train_cfg.static:
            return self._static_rollout(layout, x0, poses, dt).rollout(layout, x0, v0, poses, projection,
                                                                         stop_non_finite=True)
        xs = torch.full((x0.shape[0], steps, *x0.shape[1:]), float("nan"), dtype=x0.dtype, device=x0.device)
        vs = xs.clone()
        x, v = x0, v0
        bf16 = self.train_cfg.autocast_bf16 and x0.device.type == "cuda"  # the network in bf16, the state in fp32
        for t in range(steps):
            with torch.autocast("cuda", dtype=torch.bfloat16) if bf16 else nullcontext():
                x, v = (a[:, 0].to(x0.dtype) for a in rollout(self.model, layout, x, v, poses[:, t:t + 2], dt, projection))
            xs[:, t], vs[:, t] = x, v
            if not (torch.isfinite(x).all() and torch.isfinite(v).all()):
                break
        return xs, vs


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
