"""Training one baseline on a trajectory store: same split and holdout rule as WorldContact (wc.train.loop.prepare_data).

Writes `<out>/model.safetensors` + `model.json` under `<out>.partial/`, renamed into place when done.
The report holds the loss history, s/step, the held-out rollout position MSE of every mesh vertex
(against the zero-motion reference), measured through the public `rollout`, the validation loss zero motion and
constant velocity of the particles would have under the baseline's own loss, and the training recipe: which of
WorldContact's switches (input noise, event oversampling, checkpoint selection by held-out rollout) were on.
"""

from __future__ import annotations

import dataclasses
import shutil
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from wc.baselines import build_baseline, save_baseline
from wc.baselines.base import ParticleDynamics
from wc.baselines.config import BaselinesConfig
from wc.baselines.stopping import StopRule
from wc.data.store import TrajectoryStore
from wc.model.layout import SceneLayout, scene_layout
from wc.train.config import TrainConfig
from wc.model.past_frames import PastFrames
from wc.train.data import (LayoutBatchSampler, LayoutKey, Phase, Window, WindowDataset, layout_phase_start, overall,
                           read_phase_window)
from wc.train.evaluation import load_window, phase_rollout_errors
from wc.train.loop import prepare_data
from wc.train.noise import noisy_history

TAG_SCALE = 1.0  # the baselines do not read the layout's tag attribute


def position_statistics(store: TrajectoryStore, phases: list[Phase], max_phases: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-axis mean and std (m) of object vertex positions over (up to `max_phases`) training phases."""
    picked = phases[:: max(1, len(phases) // max_phases)][:max_phases]
    x = np.concatenate([read_phase_window(store, p, p.start, p.stop - p.start)["x"].reshape(-1, 3) for p in picked])
    return torch.tensor(x.mean(0), dtype=torch.float32), torch.tensor(np.maximum(x.std(0), 1e-3), dtype=torch.float32)


@torch.no_grad()
def validation_loss(model: ParticleDynamics, store: TrajectoryStore, windows: list[Window], length: int,
                    layout_for, device: torch.device) -> float:  # noqa: ANN001 - layout_for(key) -> SceneLayout
    """Mean training loss of the model over `windows` (one at a time)."""
    total = 0.0
    for w in windows:
        batch = load_window(store, w, length, device)
        total += float(model.window_loss(layout_for(w.phase.layout), batch["x"], batch["poses"]))
    return total / max(1, len(windows))


def reference_particle_losses(model: ParticleDynamics, p: torch.Tensor) -> tuple[float, float]:
    """The model's own loss on particle windows p (B, H + S, K, 3) [m] of two references that need no training, from
    the last observed frame t: particles that stay (zero motion), and particles that keep their last displacement,
    p_{t+k} = p_t + k (p_t - p_{t-1}) (constant velocity)."""
    h = model.history
    last, step = p[:, h - 1:h], p[:, h - 1:h] - p[:, h - 2:h - 1]
    k = torch.arange(1, p.shape[1] - h + 1, dtype=p.dtype, device=p.device)[None, :, None, None]
    return (float(model.particle_loss(last.expand_as(p[:, h:]), p[:, h:])),
            float(model.particle_loss(last + k * step, p[:, h:])))


@torch.no_grad()
def reference_losses(model: ParticleDynamics, store: TrajectoryStore, windows: list[Window], length: int,
                     layout_for, device: torch.device) -> dict[str, float]:  # noqa: ANN001 - layout_for(key) -> SceneLayout
    """Mean `reference_particle_losses` over `windows`: a baseline whose validation loss is above zero motion's has
    learned less than nothing."""
    zero = constant = 0.0
    for w in windows:
        idx = model.scene(layout_for(w.phase.layout)).particles.vertices
        z, c = reference_particle_losses(model, load_window(store, w, length, device)["x"][:, :, idx])
        zero, constant = zero + z, constant + c
    n = max(1, len(windows))
    return {"val_loss_zero_motion": zero / n, "val_loss_constant_velocity": constant / n}


def recorded_past(store: TrajectoryStore, phase: Phase, frames: int, device: torch.device) -> PastFrames | None:
    """Up to `frames` recorded frames before `phase.start` in its layout (a validation block has the episode's), as
    evaluate gives them to a baseline; None at the first frame of the layout."""
    k = min(frames, phase.start - layout_phase_start(store, phase))
    if k <= 0:
        return None
    a = read_phase_window(store, phase, phase.start - k, k)
    return PastFrames(*(torch.from_numpy(a[key])[None].to(device) for key in ("x", "v", "poses")))


def rollout_error(model: ParticleDynamics, store: TrajectoryStore, phases: list[Phase], frames: int, layout_for,
                  device: torch.device) -> dict[str, float]:  # noqa: ANN001
    """`phase_rollout_errors` of the baseline's rollouts, each given the recorded frames before its start."""
    return phase_rollout_errors(store, phases, frames, device, lambda p, batch: model.rollout(
        layout_for(p.layout), batch["x"][:, 0], batch["v"][:, 0], batch["poses"], store.dt,
        recorded_past(store, p, model.history - 1, device))[0])


def train_baseline(name: str, store_path: str | Path, out_dir: str | Path, cfg: BaselinesConfig,
                   train_cfg: TrainConfig, meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train baseline `name` with its params in `cfg.models`; write `out_dir`; return the report dict."""
    params = cfg.models[name]
    device = torch.device(cfg.device)
    torch.manual_seed(cfg.seed)
    store = TrajectoryStore(store_path)
    model = build_baseline(name, params)
    window = model.history + model.sequence
    data = prepare_data(store, dataclasses.replace(train_cfg, window=window, val_windows=cfg.val_windows, seed=cfg.seed))
    train_phases = list(dict.fromkeys(w.phase for w in data.train_windows))
    model.set_statistics(*position_statistics(store, train_phases), overall(data.scales.delta_x_m))
    model.to(device).train()
    cache: dict[LayoutKey, SceneLayout] = {}

    def layout_for(key: LayoutKey) -> SceneLayout:
        if key not in cache:
            cache[key] = scene_layout(store, list(key[0]), list(key[1]), TAG_SCALE).to(device)
        return cache[key]

    optimizer = torch.optim.Adam(model.parameters(), lr=params.lr)
    plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, factor=0.8, patience=3) if model.plateau else None
    dataset = WindowDataset(store_path, data.train_windows, window)
    weights = data.window_weights if cfg.event_oversample else None
    loader = iter(torch.utils.data.DataLoader(dataset, batch_sampler=LayoutBatchSampler(
        data.train_windows, params.batch, cfg.seed, weights=weights), num_workers=0))
    noise_m = train_cfg.input_noise_m if cfg.input_noise else 0.0
    recipe = {"input_noise_m": noise_m, "event_oversample": train_cfg.event_oversample if weights is not None else 0.0,
              "event_window_share": data.event_share if weights is not None else None, "select_by": cfg.select_by}
    picked = data.val_phases[:: max(1, len(data.val_phases) // cfg.rollout_phases)][:cfg.rollout_phases]
    references = reference_losses(model, store, data.val_windows, window, layout_for, device)
    history, recent, step_times = [], [], []
    stop = StopRule(cfg.max_minutes, cfg.patience_evals, keep_best=cfg.select_by == "rollout")
    for step in tqdm(range(1, params.steps + 1), desc=f"train {name}"):
        batch = next(loader)
        layout = layout_for(dataset.layout_keys[int(batch["layout"][0])])
        t0 = time.perf_counter()
        x = batch["x"].to(device)
        x = torch.cat([noisy_history(x[:, :model.history], noise_m), x[:, model.history:]], 1)
        loss = model.window_loss(layout, x, batch["poses"].to(device))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        recent.append(float(loss.detach()))
        step_times.append(time.perf_counter() - t0)
        if not np.isfinite(recent[-1]):
            raise FloatingPointError(f"train {name}: loss became {recent[-1]} at step {step}")
        out_of_time = stop.out_of_time()
        if step % cfg.eval_every_steps == 0 or step == params.steps or out_of_time:
            model.eval()
            val = validation_loss(model, store, data.val_windows, window, layout_for, device)
            entry = {"step": step, "train_loss": float(np.mean(recent)), "val_loss": val, **references}
            score = val
            if cfg.select_by == "rollout":
                entry.update(rollout_error(model, store, picked, cfg.rollout_frames, layout_for, device))
                score = entry["rollout_position_mse_m2"] if np.isfinite(entry["rollout_position_mse_m2"]) else np.inf
            model.train()
            if plateau is not None:
                plateau.step(val)
            history.append({**entry, "lr": optimizer.param_groups[0]["lr"]})
            recent = []
            stop.record(step, score, model)
        if out_of_time or stop.converged():
            break
    stop.restore_best(model)
    model.eval()
    errors = rollout_error(model, store, picked, cfg.rollout_frames, layout_for, device)
    out_dir, work = Path(out_dir), Path(f"{out_dir}.partial")
    shutil.rmtree(work, ignore_errors=True)
    timed = step_times[min(len(step_times) - 1, 3):]  # skip warm-up steps
    report = {"name": name, "params": dataclasses.asdict(params), "window": window, "history": history,
              "final_train_loss": history[-1]["train_loss"], "final_val_loss": history[-1]["val_loss"],
              "s_per_step_median": statistics.median(timed), "train_windows": len(data.train_windows),
              "val_windows": len(data.val_windows), "val_phases": len(data.val_phases), "rollout_phases": len(picked), "validation": data.validation,
              "particles_per_layout": {"+".join(k[0]): s.num_particles for k, s in
                                       ((k, model.scene(layout_for(k))) for k in dataset.layout_keys)},
              "train_s": float(sum(step_times)), "wall_s": stop.elapsed_s(), "steps_done": len(step_times),
              "stopped_by": stop.reason(len(step_times), params.steps), "best_step": stop.best_step,
              "best_val_loss": min(h["val_loss"] for h in history), "best_score": stop.best_val, "recipe": recipe,
              **references, **errors}
    save_baseline(model.cpu(), work, {**(meta or {}), "dt": store.dt, "steps": len(step_times),
                                      "final_val_loss": report["final_val_loss"], **errors})
    if out_dir.exists():
        shutil.rmtree(out_dir)
    work.rename(out_dir)
    return report
