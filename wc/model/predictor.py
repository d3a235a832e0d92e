"""WorldContact as a predictor: a checkpoint directory loaded in eval mode, stepping the object state of a scene
layout under prescribed body poses (the `Predictor` interface every learned method answers; rolled out as
`wc.dynamics.Dynamics` through wc.model.learned_dynamics). The expansion, evaluation and benchmarks load it here.

    x, v = predictor.rollout(layout, x0, v0, poses, dt)
    layout: wc.model.layout.SceneLayout (objects, rest topology, prescribed sample sets)
    x0, v0: (B, N, 3) torch tensors, m and m/s;  poses: (B, T, P, 7) body poses of frames 0..T-1
    returns x, v: (B, T-1, N, 3), frames 1..T-1 (non-finite values are allowed: a diverged rollout)

A predictor that reads past frames (a `history` attribute > 1: the particle baselines) also takes `past`, the
recorded frames before frame 0 (wc.model.past_frames.PastFrames), where there are any.
"""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from typing import Protocol

import torch

from wc.model.fixed_neighbors import capacities_from_dict
from wc.model.layout import SceneLayout
from wc.model.padded_neighbors import NeighborCapacity
from wc.model.rollout import rollout
from wc.model.static_rollout import StaticRollout
from wc.model.worldcontact import WorldContact
from wc.model_ref import WEIGHTS
from wc.train.capacity import initial_capacities
from wc.train.checkpoint import load_model
from wc.train.config import TrainConfig

CHECKPOINT = WEIGHTS  # a saved model folder's weights file


class Predictor(Protocol):
    def rollout(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
                dt: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicted x, v (B, T-1, N, 3) for frames 1..T-1 from x0, v0 (B, N, 3) under poses (B, T, P, 7)."""
        ...


def rollout_steps(x0: torch.Tensor, poses: torch.Tensor) -> int:
    """Steps T - 1 of a rollout from x0 (B, N, 3) under poses (B, T, P, 7); ValueError for other shapes."""
    if x0.ndim != 3 or poses.ndim != 4 or poses.shape[0] != x0.shape[0] or poses.shape[1] < 2:
        raise ValueError(f"x0 must be (B, N, 3) and poses (B, T>=2, P, 7), got {tuple(x0.shape)} and "
                         f"{tuple(poses.shape)}")
    return poses.shape[1] - 1


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

    def topology_projection(self, layout: SceneLayout):  # noqa: ANN201 - TopologyProjection | None
        """The layout's topology projection P when the checkpoint was trained with it, else None."""
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
        steps = rollout_steps(x0, poses)
        projection = self.topology_projection(layout)
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
