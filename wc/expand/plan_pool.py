"""Planning generated episodes beside the rollouts: each proposed spec is planned (wc.expand.plan.plan_episode: the
moved source state, the task program's actions, the frame-0 check) and its prescribed body poses computed (the scene's
forward kinematics), in this process (`workers` 0) or in worker processes, so that the device is not kept waiting.
Results come back as futures, in whatever order they finish; the caller consumes them in proposal order."""

from __future__ import annotations

import os
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from wc.expand.config import ExpandConfig
from wc.expand.plan import PlannedEpisode, SourceEpisode, plan_episode
from wc.model.prescribed_inputs import KinematicInputs
from wc.scene.scene import Scene
from wc.tasks.base import EpisodeSpec, InfeasibleEpisode, get_task
from wc.validate.config import ValidateConfig
from wc.worker_pool import spawn_pool


@dataclass(frozen=True)
class PlanResult:
    """A planned episode and its body poses (T, P, 7) (scene.link_names, then scene.env_names), or why it cannot be
    planned (`infeasible`)."""

    planned: PlannedEpisode | None
    poses: np.ndarray | None
    infeasible: str | None = None


class _Planner:
    def __init__(self, params: dict[str, Any], scene: Scene, sources: list[SourceEpisode], cfg: ExpandConfig,
                 dt: float, validate_cfg: ValidateConfig) -> None:
        self.task = get_task(cfg.task, params)
        self.scene, self.sources, self.cfg, self.dt, self.validate_cfg = scene, sources, cfg, dt, validate_cfg
        self.inputs = KinematicInputs(scene)

    def __call__(self, spec: EpisodeSpec, source: int) -> PlanResult:
        try:
            planned = plan_episode(self.task, self.scene, self.sources[source], spec, self.cfg, self.dt,
                                   self.validate_cfg)
        except InfeasibleEpisode as err:
            return PlanResult(None, None, str(err))
        return PlanResult(planned, self.inputs.poses(planned.actions[None])[0])


_WORKER: _Planner | None = None


def _init_worker(*args: Any) -> None:
    global _WORKER
    torch.set_num_threads(1)  # many planners share the host's cores; each plan's IK is small
    _WORKER = _Planner(*args)


def _plan_in_worker(spec: EpisodeSpec, source: int) -> PlanResult:
    return _WORKER(spec, source)


class PlanPool:
    """Plans specs in `workers` spawned processes (0: here, at submit), one torch thread each."""

    def __init__(self, params: dict[str, Any], scene: Scene, sources: list[SourceEpisode], cfg: ExpandConfig,
                 dt: float, validate_cfg: ValidateConfig, workers: int) -> None:
        args = (params, scene, sources, cfg, dt, validate_cfg)
        self._local = _Planner(*args) if workers == 0 else None
        # spawned (a forked worker cannot use autograd once the parent has, as the IK does, nor CUDA), ending with
        # the stage even when it is killed
        self._pool = None if workers == 0 else spawn_pool(workers, initializer=_init_worker, initargs=args)
        for _ in range(workers):  # start every worker now (a spawned pool starts one per submit): their imports and
            self._pool.submit(os.getpid)  # planners load while the stage loads its model, not while the slots wait

    def submit(self, spec: EpisodeSpec, source: int) -> Future[PlanResult]:
        if self._pool is not None:
            return self._pool.submit(_plan_in_worker, spec, source)
        done: Future[PlanResult] = Future()
        done.set_result(self._local(spec, source))
        return done

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> PlanPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
