"""Training WorldContact: base stage, then the projection stage, on one process or under torchrun (DDP).

Output directory (written under `<out>.partial/`, renamed into place when both stages finish, so an
interrupted run leaves no half-written model; `resume=True` continues from the partial's last state):
    model.safetensors + model.json   the lower best validation loss of the two stages (its json says
                                     whether it rolls out with the projection)
    base.safetensors + base.json     best of the base stage
    last.safetensors + last.json, last_state.pt   the latest step (resume)
"""

from __future__ import annotations

import shutil
import statistics
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.fixed_neighbors import FixedNeighbors, capacities_from_dict, capacities_to_dict
from wc.model.layout import SceneLayout, scene_layout
from wc.model.rollout import Step, rollout
from wc.model.worldcontact import WorldContact
from wc.model_ref import model_record
from wc.train import distributed
from wc.train.capacity import data_capacities
from wc.train.checkpoint import load_state, model_scales, restore_rng_states, rng_states, save_state, save_weights
from wc.train.config import TrainConfig
from wc.train.data import (LayoutBatchSampler, LayoutKey, Phase, Scales, Window, WindowDataset, data_scales,
                           phases_of, split_blocks, windows_of)
from wc.train.events import window_weights
from wc.train.evaluation import rollout_error, segment_loss, validation_losses
from wc.train.selection import selection_score, shipped_stage
from wc.train.noise import noisy_state
from wc.train.warm_start import pretrained_model
from wc.train.resident import ResidentWindows
from wc.train.schedule import learning_rate
from wc.train.static_step import StaticTrainer, StepSettings, make_optimizer, set_learning_rate


@dataclass
class TrainData:
    """Which windows train, which validate, and the data scales."""

    train_windows: list[Window]
    train_phases: list[Phase]
    val_windows: list[Window]  # fixed, seeded subset
    val_phases: list[Phase]  # held-out rollouts
    scales: Scales
    validation: str  # how validation data was chosen
    window_weights: np.ndarray | None = None  # sampling weight per train window (None: uniform; wc.train.events)
    event_share: float = float("nan")  # share of train windows near a contact event


def prepare_data(store: TrajectoryStore, cfg: TrainConfig) -> TrainData:
    """Windows of the train split; validation from the val split, else from held-out tails of train episodes."""
    train_phases = phases_of(store, "train")
    if not train_phases:
        raise ValueError(f"{store.path}: no train episodes")
    val_phases = phases_of(store, "val")
    validation = "val split"
    if not val_phases and cfg.select_by == "rollout":
        raise ValueError(f"{store.path}: train.select_by rollout scores checkpoints on whole held-out episodes, and the "
                         "store has no val split (set validate.val_per_task >= 1, or train.select_by val_loss)")
    if not val_phases:
        train_phases, val_phases = split_blocks(train_phases, cfg.holdout_fraction, cfg.holdout_block_frames,
                                                cfg.window)
        validation = (f"every {max(2, round(1 / cfg.holdout_fraction))}th block of {cfg.holdout_block_frames} frames "
                      f"of each train episode (the store has no val split)")
    train_windows = windows_of(train_phases, cfg.window)
    val_all = windows_of(val_phases, cfg.window)
    if not train_windows or not val_all:
        raise ValueError(f"{store.path}: {len(train_windows)} train and {len(val_all)} validation windows of "
                         f"{cfg.window} frames; need at least one of each")
    pick = np.random.default_rng(cfg.seed).permutation(len(val_all))[: cfg.val_windows]
    weights, share = window_weights(store, train_phases, train_windows, cfg.window, cfg.event_oversample,
                                    cfg.event_margin_frames, cfg.event_accel_m_s2)
    return TrainData(train_windows, train_phases, [val_all[i] for i in sorted(pick)], val_phases,
                     data_scales(store, train_phases, cfg.stats_episodes, cfg.per_axis_scales), validation, weights,
                     share)


class SegmentRollout(nn.Module):
    """The whole W-step rollout as one forward, so DDP sees one forward per backward."""

    def __init__(self, model: WorldContact) -> None:
        super().__init__()
        self.model = model

    def forward(self, layout: SceneLayout, x0: torch.Tensor, v0: torch.Tensor, poses: torch.Tensor, dt: float,
                projection: nn.Module | None, neighbors: FixedNeighbors | None = None,
                step: Step | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        return rollout(self.model, layout, x0, v0, poses, dt, projection, neighbors=neighbors, step=step)


def _layouts(store: TrajectoryStore, model_cfg: ModelConfig, device: torch.device):  # noqa: ANN202
    cache: dict[LayoutKey, SceneLayout] = {}

    def layout_for(key: LayoutKey) -> SceneLayout:
        if key not in cache:
            cache[key] = scene_layout(store, list(key[0]), list(key[1]), model_cfg.tag_scale).to(device)
        return cache[key]
    return layout_for


class ReferenceSteps:
    """The reference path: windows read from the store through a DataLoader, pair-list neighbours, eager."""

    def __init__(self, store_path: str | Path, data: TrainData, sampler: LayoutBatchSampler, runner: nn.Module,
                 optimizer: torch.optim.Optimizer, cfg: TrainConfig, dt: float, device: torch.device,
                 layout_for) -> None:  # noqa: ANN001
        self.dataset = WindowDataset(store_path, data.train_windows, cfg.window)
        self.loader = iter(torch.utils.data.DataLoader(self.dataset, batch_sampler=sampler,
                                                       num_workers=cfg.num_workers))
        self.runner, self.optimizer, self.cfg, self.dt, self.device = runner, optimizer, cfg, dt, device
        self.layout_for = layout_for

    def step(self, projector, step_number: int) -> float:  # noqa: ANN001
        batch = next(self.loader)
        layout = self.layout_for(self.dataset.layout_keys[int(batch["layout"][0])])
        x, v, poses = (batch[k].to(self.device) for k in ("x", "v", "poses"))
        loss = optimisation_step(self.runner, self.optimizer, layout, x, v, poses, self.dt, projector(layout), self.cfg)
        if distributed.world_size() > 1:  # every rank sees the mean loss, so all stop on a non-finite one
            loss = float(distributed.summed(torch.tensor([loss], device=self.device))) / distributed.world_size()
        if not np.isfinite(loss):
            raise FloatingPointError(f"train: loss became {loss} at step {step_number}")
        return loss


class StaticSteps:
    """The static-shape path: resident windows, fixed-K neighbours, optionally compiled and CUDA-graphed."""

    def __init__(self, resident: ResidentWindows, sampler: LayoutBatchSampler, trainer: StaticTrainer,
                 layout_for) -> None:  # noqa: ANN001
        self.resident, self.sampler, self.trainer, self.layout_for = resident, iter(sampler), trainer, layout_for

    def step(self, projector, step_number: int) -> float:  # noqa: ANN001
        li, starts = self.resident.batch_location(next(self.sampler))
        layout = self.layout_for(self.resident.layout_keys[li])
        return self.trainer.step(li, layout, self.resident.layouts[li], starts, projector(layout), step_number)


def rank_streams(state: dict[str, Any], procs: distributed.Processes) -> dict[str, Any]:
    """This rank's sampler and RNG streams from a saved training state (a state saved before per-rank streams has
    rank 0's alone). An exact resume needs the process count the state was saved with."""
    ranks = state.get("ranks") or [{"sampler": state["sampler"], "rng": state["rng"]}]
    if len(ranks) != procs.world_size:
        raise ValueError(f"training state saved by {len(ranks)} process(es), resumed with {procs.world_size}: resume "
                         f"with the same process count (torchrun --nproc-per-node {len(ranks)})")
    return ranks[procs.rank]


def train(store_path: str | Path, out_dir: str | Path, model_cfg: ModelConfig, cfg: TrainConfig, *,
          resume: bool = False, meta: dict[str, Any] | None = None, stop_at_step: int | None = None) -> dict[str, Any]:
    """Train both stages; returns the report dict (rank 0's; other ranks return {}).

    A run stops early, with a complete checkpoint in `<out>.partial/`, after `cfg.max_minutes` of wall time or at
    `stop_at_step`; it then returns {"complete": False, "step": ...} and `resume=True` continues it to the same
    result as an uninterrupted run (weights, optimizer, sampler, RNG streams and capacities are all restored).
    """
    cfg = cfg.run_config()
    procs = distributed.start(cfg.device)
    started = time.monotonic()
    if cfg.tf32 and procs.device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    torch.manual_seed(cfg.seed)
    store = TrajectoryStore(store_path)
    data = prepare_data(store, cfg)
    out_dir, work = Path(out_dir), Path(f"{out_dir}.partial")
    if cfg.init_from:  # fine-tune: the network and its output scales are the checkpoint's
        model = pretrained_model(cfg.init_from, model_cfg)[0].to(procs.device)
    else:
        model = WorldContact(model_cfg, **asdict(data.scales)).to(procs.device)
    layout_for = _layouts(store, model_cfg, procs.device)
    optimizer = make_optimizer(model, cfg, procs.device)
    sampler = LayoutBatchSampler(data.train_windows, cfg.batch_size, cfg.seed, procs.rank, data.window_weights,
                                 shared_layouts=procs.distributed)
    step, history, recent, best = 0, [], [], {"base": float("inf"), "projection": float("inf")}
    capacities, measured = None, None
    state_path = work / "last_state.pt"
    state = load_state(state_path) if resume and state_path.is_file() else None
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        step, history, best = state["step"], state["history"], state["best"]
        if state.get("capacities"):
            capacities, measured = capacities_from_dict(state["capacities"]), state.get("measured_neighbors")
        recent = state.get("recent", [])
        streams = rank_streams(state, procs)
        sampler.set_state(streams["sampler"])
    elif procs.main:
        shutil.rmtree(work, ignore_errors=True)
    distributed.barrier(procs)
    work.mkdir(parents=True, exist_ok=True)
    runner: nn.Module = SegmentRollout(model)
    graphed = cfg.static and cfg.cuda_graph and procs.device.type == "cuda"
    if procs.distributed:  # built on a side stream where its backward will be captured in a CUDA graph (torch's rule)
        with torch.cuda.stream(torch.cuda.Stream(procs.device)) if graphed else nullcontext():
            runner = DistributedDataParallel(runner, device_ids=[procs.device] if procs.device.type == "cuda" else None)
    if cfg.static:
        if capacities is None:
            capacities, measured = data_capacities(store, data.train_phases, model_cfg, layout_for,
                                                   cfg.neighbor_headroom, procs.device)
        settings = StepSettings.of(cfg, store.dt)
        trainer = StaticTrainer(model, runner, optimizer, capacities, settings)
        trainer.grown = list(state.get("neighbor_growth", [])) if state is not None else []
        steps: ReferenceSteps | StaticSteps = StaticSteps(
            ResidentWindows(store, data.train_windows, cfg.window, procs.device), sampler, trainer, layout_for)
    else:
        trainer = None
        steps = ReferenceSteps(store_path, data, sampler, runner, optimizer, cfg, store.dt, procs.device, layout_for)

    if state is not None:  # after the set-up above, which draws (e.g. the DataLoader's seed)
        restore_rng_states(streams["rng"], procs.device)

    def neighbors_for(layout: SceneLayout) -> FixedNeighbors | None:
        return model.fixed_neighbors(layout, trainer.capacities) if trainer is not None else None

    def checkpoint() -> None:
        """Rank 0 saves; every rank contributes its own sampler and RNG streams (a collective: all ranks call it)."""
        ranks = distributed.gathered(procs, {"sampler": sampler.state(), "rng": rng_states(procs.device)})
        if not procs.main:
            return
        save_weights(model, work / "last.safetensors", {**meta, **static_meta(), "step": step, "stage": stage,
                                                        "projection": stage == "projection"})
        save_state(state_path, {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                                "history": history, "best": best, "recent": recent, "ranks": ranks,
                                **static_meta()})

    def static_meta() -> dict[str, Any]:
        if trainer is None:
            return {}
        return {"capacities": capacities_to_dict(trainer.capacities), "measured_neighbors": measured,
                "neighbor_growth": trainer.grown}

    total = cfg.base.steps + cfg.projection.steps
    step_times: list[float] = []
    meta = {**(meta or {}), "dt": store.dt, "validation": data.validation, "init_from": cfg.init_from}
    bar = tqdm(total=total, initial=step, desc="train", disable=not procs.main)
    stopped = False
    stage = "base" if step < cfg.base.steps else "projection"
    while step < total and not stopped:
        stage = "base" if step < cfg.base.steps else "projection"
        schedule = cfg.base if stage == "base" else cfg.projection
        lr = learning_rate(schedule, step if stage == "base" else step - cfg.base.steps)
        set_learning_rate(optimizer, lr)
        projector = _projector(model, cfg, stage)
        t0 = time.perf_counter()
        recent.append(steps.step(projector, step))
        step_times.append(time.perf_counter() - t0)
        step += 1
        bar.update(1)
        stage_end = step in (cfg.base.steps, total)
        if procs.main and (step % cfg.eval_every_steps == 0 or stage_end):
            losses = validation_losses(model, store, data.val_windows, cfg.window, layout_for, projector, store.dt,
                                       cfg.lambda_x, cfg.lambda_v, procs.device, cfg.batch_size, neighbors_for)
            losses.update(rollout_error(model, store, data.val_phases, cfg.rollout_frames, layout_for, projector,
                                        store.dt, procs.device, neighbors_for, cfg.select_max_strain))
            losses["score"] = selection_score(losses, cfg.select_by)
            history.append({"step": step, "stage": stage, "lr": lr, "train_loss": float(np.mean(recent)), **losses})
            recent = []
            bar.set_postfix(train=f"{history[-1]['train_loss']:.3g}", val=f"{losses['val_loss']:.3g}")
            first = not any(h["stage"] == stage for h in history[:-1])  # saved even when it diverged: a stage ships something
            if losses["score"] < best[stage] or first:
                best[stage] = losses["score"]
                save_weights(model, work / f"{stage}.safetensors",
                             {**meta, **static_meta(), "step": step, "stage": stage,
                              "projection": stage == "projection", **losses})
        out_of_time = cfg.max_minutes > 0 and time.monotonic() - started > 60.0 * cfg.max_minutes
        if procs.distributed and cfg.max_minutes > 0:  # the ranks' clocks differ: all stop when one is out of time
            out_of_time = distributed.any_rank(out_of_time, procs.device)
        stopped = step < total and (out_of_time or (stop_at_step is not None and step >= stop_at_step))
        if step % cfg.checkpoint_every_steps == 0 or stage_end or stopped:
            checkpoint()
    bar.close()
    distributed.barrier(procs)
    report: dict[str, Any] = {}
    if procs.main and stopped:
        report = {"complete": False, "step": step, "total_steps": total, "partial": str(work),
                  "s_per_step_median": statistics.median(step_times) if step_times else float("nan")}
    elif procs.main:
        report = _finish(model, work, out_dir, cfg, data, history, step_times, procs)
        report.update(static_meta())
    distributed.barrier(procs)
    if trainer is not None:
        trainer.release()
    distributed.stop(procs)
    return report


def optimisation_step(runner: nn.Module, optimizer: torch.optim.Optimizer, layout: SceneLayout, x: torch.Tensor,
                      v: torch.Tensor, poses: torch.Tensor, dt: float, projection: nn.Module | None,
                      cfg: TrainConfig) -> float:
    """One AdamW step on a batch of windows x, v (B, W, N, 3), poses (B, W, P, 7); returns the loss (synchronised).
    The reference path (pair-list neighbours, eager)."""
    autocast = cfg.autocast_bf16 and x.device.type == "cuda"
    x0, v0 = noisy_state(x[:, 0], v[:, 0], cfg.input_noise_m, dt)
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=autocast):
        xp, vp = runner(layout, x0, v0, poses, dt, projection)
    loss = segment_loss(xp.float(), vp.float(), x[:, 1:], v[:, 1:], cfg.lambda_x, cfg.lambda_v)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if cfg.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_([p for g in optimizer.param_groups for p in g["params"]], cfg.grad_clip)
    optimizer.step()
    return float(loss.detach())  # waits for the device: the step is complete when this returns


def _projector(model: WorldContact, cfg: TrainConfig, stage: str):  # noqa: ANN202
    if stage == "base":
        return lambda layout: None
    return lambda layout: model.projection(layout, cfg.smoothing_iterations, cfg.smoothing_weight,
                                           cfg.constraint_iterations, cfg.edge_ratio)


def _finish(model: WorldContact, work: Path, out_dir: Path, cfg: TrainConfig, data: TrainData,
            history: list[dict[str, Any]], step_times: list[float], procs: distributed.Processes) -> dict[str, Any]:
    """Promote the best stage's best weights to model.*, rename the work dir into place, build the report.

    `train.ship_stage` says which stage (wc/train/selection.py): `best` compares both stages' best scores on the same
    windows, `last` ships the projection stage whenever it ran.
    """
    best = {stage: min((h["score"] for h in history if h["stage"] == stage), default=float("inf"))
            for stage in ("base", "projection") if (work / f"{stage}.safetensors").is_file()}
    final = shipped_stage(best, cfg.ship_stage)
    if not np.isfinite(best[final]) and cfg.select_by == "rollout":
        print(f"train: WARNING every evaluation's held-out rollouts diverged; shipping the {final} stage's first "
              "checkpoint", flush=True)
    for suffix in (".safetensors", ".json"):
        shutil.copyfile(work / f"{final}{suffix}", work / f"model{suffix}")
    if out_dir.exists():
        shutil.rmtree(out_dir)
    work.rename(out_dir)
    timed = step_times[min(len(step_times) - 1, 5):] if step_times else []  # skip warm-up steps
    step_s = statistics.median(timed) if timed else float("nan")
    last = history[-1] if history else {}
    return {
        "parameters": model.parameter_counts(), "final_stage": final, "validation": data.validation,
        "steps": {"base": cfg.base.steps, "projection": cfg.projection.steps},
        "train_windows": len(data.train_windows), "val_windows": len(data.val_windows),
        "event_window_share": data.event_share, "event_oversample": cfg.event_oversample,
        "scales": model_scales(model), "init_from": cfg.init_from,
        "init_model": model_record(cfg.init_from) if cfg.init_from else None, "history": history,
        "selected_by": cfg.select_by, "best_score": best[final],
        "selected": next((h for h in history if h["stage"] == final and h["score"] == best[final]), {}),
        "best_val_loss": min((h["val_loss"] for h in history if h["stage"] == final), default=float("nan")),
        "best_val_loss_by_stage": {stage: min(h["val_loss"] for h in history if h["stage"] == stage)
                                   for stage in best if any(h["stage"] == stage for h in history)},
        "zero_motion_val_loss": last.get("zero_motion_loss", float("nan")),
        "constant_velocity_val_loss": last.get("constant_velocity_loss", float("nan")),
        "rollout_position_mse_m2": last.get("rollout_position_mse_m2", float("nan")),
        "rollout_zero_motion_mse_m2": last.get("rollout_zero_motion_mse_m2", float("nan")),
        "s_per_step_median": step_s, "processes": procs.world_size,
        "samples_per_s": cfg.batch_size * procs.world_size / step_s if step_s == step_s else float("nan"),
        "window": cfg.window, "batch_size": cfg.batch_size, "autocast_bf16": cfg.autocast_bf16,
    }
