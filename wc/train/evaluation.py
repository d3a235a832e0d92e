"""Validation during training: segment loss, the zero-motion reference, held-out rollout error."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from wc.data.store import TrajectoryStore
from wc.model.fixed_neighbors import FixedNeighbors
from wc.model.layout import SceneLayout
from wc.model.rollout import rollout, rollout_within_capacity
from wc.model.worldcontact import WorldContact
from wc.train.data import LayoutKey, Phase, Window, read_phase_window
from wc.train.selection import max_edge_strain

LayoutFor = Callable[[LayoutKey], SceneLayout]
Projector = Callable[[SceneLayout], object]  # layout -> TopologyProjection | None


def segment_loss(x_pred: torch.Tensor, v_pred: torch.Tensor, x_true: torch.Tensor, v_true: torch.Tensor,
                 lambda_x: float, lambda_v: float) -> torch.Tensor:
    """Paper Eq. loss: mean over batch, steps and vertices of λx‖x̂ − x‖² + λv‖v̂ − v‖²."""
    return (lambda_x * (x_pred - x_true).square().sum(-1) + lambda_v * (v_pred - v_true).square().sum(-1)).mean()


def load_window(store: TrajectoryStore, window: Window, length: int, device: torch.device) -> dict[str, torch.Tensor]:
    """One window as a batch of 1 on `device`."""
    arrays = read_phase_window(store, window.phase, window.start, length)
    return {k: torch.from_numpy(np.ascontiguousarray(a))[None].to(device) for k, a in arrays.items()}


NeighborsFor = Callable[[SceneLayout], FixedNeighbors | None]  # layout -> static-shape neighbours (None: reference)


def _rollout(model: WorldContact, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor,
             dt: float, projection: object, neighbors: FixedNeighbors | None) -> tuple[torch.Tensor, torch.Tensor]:
    if neighbors is None:
        return rollout(model, layout, x0, v0, poses, dt, projection)
    return rollout_within_capacity(model, layout, x0, v0, poses, dt, projection, neighbors)[:2]


@torch.no_grad()
def validation_losses(model: WorldContact, store: TrajectoryStore, windows: list[Window], length: int,
                      layout_for: LayoutFor, projector: Projector, dt: float, lambda_x: float, lambda_v: float,
                      device: torch.device, batch_size: int = 1,
                      neighbors_for: NeighborsFor | None = None) -> dict[str, float]:
    """Mean segment loss of the model and of two references over `windows`, rolled out `batch_size` windows of
    one layout at a time (static-shape neighbours when `neighbors_for` gives them).

    Zero motion: x stays where it is, v = 0. Constant velocity: x_k = x_0 + k·v_0·dt, v_k = v_0 (what an
    untrained model, whose head starts near zero change, predicts).
    """
    was_training = model.training
    model.eval()
    model_sum = zero_sum = const_sum = 0.0
    by_layout: dict[LayoutKey, list[Window]] = {}
    for w in windows:
        by_layout.setdefault(w.phase.layout, []).append(w)
    for key, group in by_layout.items():
        layout = layout_for(key)
        for s in range(0, len(group), batch_size):
            loaded = [load_window(store, w, length, device) for w in group[s:s + batch_size]]
            x, v, poses = (torch.cat([b[k] for b in loaded]) for k in ("x", "v", "poses"))
            xp, vp = _rollout(model, layout, x[:, 0], v[:, 0], poses, dt, projector(layout),
                              neighbors_for(layout) if neighbors_for else None)
            n = x.shape[0]  # segment_loss means over the batch: weigh each chunk by its windows
            model_sum += n * float(segment_loss(xp, vp, x[:, 1:], v[:, 1:], lambda_x, lambda_v))
            still_x = x[:, :1].expand_as(x[:, 1:])  # zero motion: x stays, v = 0
            zero_sum += n * float(segment_loss(still_x, torch.zeros_like(still_x), x[:, 1:], v[:, 1:], lambda_x,
                                               lambda_v))
            k = torch.arange(1, length, device=device, dtype=x.dtype)[None, :, None, None]
            const_x, const_v = x[:, :1] + k * dt * v[:, :1], v[:, :1].expand_as(still_x)
            const_sum += n * float(segment_loss(const_x, const_v, x[:, 1:], v[:, 1:], lambda_x, lambda_v))
    model.train(was_training)
    n = max(1, len(windows))
    return {"val_loss": model_sum / n, "zero_motion_loss": zero_sum / n, "constant_velocity_loss": const_sum / n}


RolloutPredictor = Callable[[Phase, dict[str, torch.Tensor]], torch.Tensor]  # (phase, batch) -> x̂ (1, T-1, N, 3)


@torch.no_grad()
def phase_rollout_errors(store: TrajectoryStore, phases: list[Phase], frames: int, device: torch.device,
                         predict: RolloutPredictor) -> dict[str, float]:
    """Position MSE (m², mean over vertices and frames of ‖x̂ − x‖²) of `predict`'s rollouts from each phase's
    first frame over up to `frames` steps, and of zero motion on the same frames."""
    errors, zero = [], []
    for p in phases:
        length = min(frames + 1, p.stop - p.start)
        if length < 2:
            continue
        batch = load_window(store, Window(p, p.start), length, device)
        x = batch["x"]
        errors.append(float((predict(p, batch) - x[:, 1:]).square().sum(-1).mean()))
        zero.append(float((x[:, :1] - x[:, 1:]).square().sum(-1).mean()))
    if not errors:
        return {"rollout_position_mse_m2": float("nan"), "rollout_zero_motion_mse_m2": float("nan")}
    return {"rollout_position_mse_m2": float(np.mean(errors)), "rollout_zero_motion_mse_m2": float(np.mean(zero))}


@torch.no_grad()
def rollout_error(model: WorldContact, store: TrajectoryStore, phases: list[Phase], frames: int,
                  layout_for: LayoutFor, projector: Projector, dt: float, device: torch.device,
                  neighbors_for: NeighborsFor | None = None, max_strain: float = math.inf) -> dict[str, float]:
    """`phase_rollout_errors` of WorldContact's autoregressive rollouts (eval mode, the stage's projection), with the
    largest rest-edge strain of any rollout and how many rollouts diverged (non-finite, or strain > max_strain)."""
    strains: list[float] = []

    def predict(p: Phase, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        layout = layout_for(p.layout)
        x_pred = _rollout(model, layout, batch["x"][:, 0], batch["v"][:, 0], batch["poses"], dt, projector(layout),
                          neighbors_for(layout) if neighbors_for else None)[0]
        strains.append(max_edge_strain(x_pred, layout.edges, layout.rest_lengths))
        return x_pred

    was_training = model.training
    model.eval()
    try:
        errors = phase_rollout_errors(store, phases, frames, device, predict)
    finally:
        model.train(was_training)
    return {**errors, "rollout_max_strain": max(strains, default=math.nan),
            "rollout_diverged": sum(not strain <= max_strain for strain in strains)}
