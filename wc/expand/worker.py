"""An expand work unit: one batch of planned episodes rolled out by the world model (contact-projected after every
step, per `expand.projection`) and judged by the source data's checks. `ExpandWorker` does it, in the stage's
process (local executor) or in a Ray worker process (`load_expand_worker`); the planning and the writing stay in
the stage (wc.expand.stage)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.devices import resolve_device, resolve_warp_device
from wc.model.predictor import WorldContactPredictor
from wc.expand.batched_rollout import Rollout, rollout_batch
from wc.expand.carry import PadCarry
from wc.expand.config import ExpandConfig
from wc.expand.constraints import JointStepProjection
from wc.expand.contact import ContactProjectedPredictor
from wc.expand.crossing_free import CrossingFreeStep
from wc.expand.plan import PlannedEpisode, source_episodes
from wc.expand.self_contact import SelfContactSeparation
from wc.expand.untangle import SelfIntersectionGuard
from wc.model.layout import scene_layout
from wc.reports import environment_info
from wc.scene.config import SceneConfig
from wc.scene.scene import Scene
from wc.sim.config import SimConfig
from wc.tasks.base import Task, get_task
from wc.train.config import TrainConfig
from wc.validate.config import ValidateConfig
from wc.validate.failure_detail import failure_detail
from wc.validate.predicates import Episode, first_failure
from wc.scene.episode_scenes import EpisodeScenes

Counters = dict[str, dict[str, float]]  # the projection's counters by part: projection, untangle, then


def verdict(task: Task, scene: Scene, task_check: bool, planned: PlannedEpisode, r: Rollout,
            cfg: ValidateConfig, frame_dt_s: float) -> tuple[str, int] | None:
    """(first failing check, frame) of a generated episode: the source data's predicates, then (if asked) the
    task's own verdict on the last frame; None when it passes."""
    failure = first_failure(scene, r.x, r.v, r.action, r.link_poses, cfg, frame_dt_s=frame_dt_s)
    if failure is not None or not task_check:
        return failure
    reason = task.check(scene, planned.spec, r.x, r.action)
    return (reason, len(r.x) - 1) if reason else None


def _failure_detail(scene: Scene, r: Rollout, cfg: ValidateConfig, dt: float, reason: str,
                    frame: int) -> dict[str, Any]:
    """A blow_up's sub-criterion (speed or strain) and both values at its frame, a penetration's body and depth;
    nothing for other reasons."""
    return failure_detail(scene, Episode(r.x, r.v, r.action, r.link_poses, dt), cfg, reason, frame)


def joint_projection(cfg: ExpandConfig, scene: Scene, sim: SimConfig, validate_cfg: ValidateConfig
                     ) -> JointStepProjection | None:
    """The per-step projection `expand.projection: joint` asks for, with its options; None for the others."""
    if cfg.projection != "joint":
        return None
    carry = PadCarry(scene, cfg.pad_carry_radius_m) if cfg.pad_carry else None
    def rollback() -> SelfIntersectionGuard:
        return SelfIntersectionGuard(scene, cfg.untangle_rounds, resolve_warp_device(validate_cfg.device, "validate.device"))

    untangle = {"none": lambda: None, "rollback": rollback,
                "bounded": lambda: CrossingFreeStep(scene, cfg.untangle_share, cfg.untangle_rounds),
                "bounded+rollback": lambda: CrossingFreeStep(scene, cfg.untangle_share, cfg.untangle_rounds, hold=False,
                                                             then=rollback())}[cfg.untangle]()
    self_contact = (SelfContactSeparation(scene, sim.self_contact_gap_m, sim.self_contact_filter_rings)
                    if cfg.self_contact else None)
    return JointStepProjection(scene, cfg.projection_edge_ratio, cfg.projection_iterations, carry,
                               untangle, self_contact, cfg.projection_final_edge_passes)


def projection_counters(projection: JointStepProjection | None) -> Counters:
    """The live counters of the projection and of its self-crossing guards (the guard's follow-up under 'then')."""
    guard = projection.untangle if projection is not None else None
    then = getattr(guard, "then", None)
    parts = {"projection": projection, "untangle": guard, "then": then}
    return {name: part.stats for name, part in parts.items() if part is not None}


def merged_counters(total: Counters, part: Counters) -> Counters:
    """Counters of two sets of batches together: maxima (keys max_*) the larger, the others summed."""
    return {name: {k: (max(total[name][k], v) if k.startswith("max_") else total[name][k] + v) if name in total else v
                   for k, v in counters.items()} for name, counters in part.items()}


@dataclass
class ExpandBatch:
    """What one expand work unit gives back to the stage, per planned episode in order and in total."""

    rollouts: list[Rollout]
    failures: list[tuple[str, int] | None]  # (first failing check, frame); None: accepted
    details: list[dict[str, Any]]  # a blow_up's sub-criterion or a penetration's body (_failure_detail); {} otherwise
    rollout_s: float  # world-model time (the checks not counted)
    counters: Counters  # the projection's counters over this batch alone
    device: str
    environment: dict[str, str]  # where it ran (wc.reports.environment_info)


class ExpandWorker:
    """The world model of `model_dir` on `expand.device`, with the projection `expand.projection` asks for, in the
    layout of `src`'s episodes of `scene`: rolls out batches of planned episodes and judges them."""

    def __init__(self, params: dict[str, Any], model_dir: str | Path, scene: Scene, src: TrajectoryStore) -> None:
        cfg = load_section(params, "expand", ExpandConfig)
        self.cfg, self.scene, self.dt = cfg, scene, src.dt
        self.validate_cfg = load_section(params, "validate", ValidateConfig)
        self.task = get_task(cfg.task, params)
        self.device = resolve_device(cfg.device, "expand.device")
        torch.manual_seed(cfg.seed)
        model = WorldContactPredictor.from_dir(Path(model_dir), load_section(params, "train", TrainConfig), self.device)
        self.layout = scene_layout(src, list(scene.objects), list(scene.link_names), model.tag_scale).to(self.device)
        self.projection = joint_projection(cfg, scene, load_section(params, "sim", SimConfig), self.validate_cfg)
        self.predictor = model if cfg.projection == "none" else ContactProjectedPredictor(model, scene, self.projection)
        self.environment = environment_info(str(self.device))

    def __call__(self, planned: list[PlannedEpisode]) -> ExpandBatch:
        counters = projection_counters(self.projection)
        for part in counters.values():  # count this batch alone
            part.update({k: type(v)(0) for k, v in part.items()})
        started = time.perf_counter()
        rollouts = rollout_batch(self.predictor, self.layout, self.scene, planned, self.dt, self.device)
        rollout_s = time.perf_counter() - started
        failures = [verdict(self.task, self.scene, self.cfg.task_check, p, r, self.validate_cfg, self.dt)
                    for p, r in zip(planned, rollouts)]
        details = [_failure_detail(self.scene, r, self.validate_cfg, self.dt, *f) if f else {}
                   for r, f in zip(rollouts, failures)]
        return ExpandBatch(rollouts, failures, details, rollout_s, {k: dict(v) for k, v in counters.items()},
                           str(self.device), self.environment)


def load_expand_worker(params: dict[str, Any], model_dir: str, store: str) -> ExpandWorker:
    """`ExpandWorker` in a Ray worker process: the task's scene from the source store, as the stage builds it (the
    paths must be readable there: one machine, or a shared file system)."""
    src = TrajectoryStore(store)
    task = get_task(load_section(params, "expand", ExpandConfig).task, params)
    _, scene = source_episodes(src, task, EpisodeScenes(load_section(params, "scene", SceneConfig), src))
    return ExpandWorker(params, model_dir, scene, src)
