"""The closed-loop trials of every policy, in this process or spread over `policy_eval.workers` processes.

A trial depends only on its policy and seed (the env resets the physics, the actor its queue, torch its seed),
so trials can run in any process and order; the results come back sorted as the jobs were listed. Each worker
builds one env and loads each policy once, on its first trial of that policy. Workers are spawned and end with the
stage (wc.worker_pool). On one GPU the processes time-slice it: 12 workers on an H100 ran 150 trials only
~1.6x as fast as one process (reports/gpu/policy_h100_three_arms.md), so a few workers get most of the gain.

With `policy_eval.batch` N > 0 a unit of work is up to N consecutive trials of one policy, run at once as the worlds
of one Newton model (wc.policy_eval.batched_env), the policy called once per step for all of them; every policy's
trials are cut into the same batches.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from concurrent.futures import as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from wc.config import load_section
from wc.policy_eval.config import PolicyEvalConfig
from wc.worker_pool import cores_each, spawn_pool

if TYPE_CHECKING:
    from wc.policy_eval.batched_env import BatchedLiftEnv
    from wc.policy_eval.closed_loop import PolicyActor

# lerobot, Newton and the renderer are imported where a trial runs (TrialRunner), not on import: the stage's parent
# process only hands jobs to its spawned workers, and importing them there cost ~25 s of every policy_eval run


@dataclass(frozen=True)
class TrialJob:
    policy: str  # policy name (its dataset)
    path: str  # the saved policy's directory
    index: int  # trial index: the same seeds for every policy
    seed: int  # trial seed
    record: bool  # write this trial's mp4

    @property
    def video_name(self) -> str:
        return f"{self.policy}_trial{self.index:02d}_seed{self.seed}.mp4"


@dataclass(frozen=True)
class TrialResult:
    job: TrialJob
    outcome: dict[str, Any]  # TrialOutcome.to_json()
    s_per_step: float  # batched: the batch's seconds per step (one step advances all its trials)
    env_seconds: dict[str, float]  # this trial's share of the env's reset / physics / render seconds
    load_s: float  # seconds loading the policy before this trial (0 when the process had it)


def trial_jobs(policies: dict[str, Path], seeds: list[int], videos: int) -> list[TrialJob]:
    """Trial-major: trial 0 of every policy, then trial 1, ... (an interrupted run has every policy as far)."""
    return [TrialJob(name, str(path), i, seed, i < videos) for i, seed in enumerate(seeds)
            for name, path in policies.items()]


def trial_units(jobs: list[TrialJob], batch: int) -> list[list[TrialJob]]:
    """The jobs as a runner takes them: each alone (batch 0), or per policy `batch` consecutive trials at a time, the
    first batch of every policy, then the second, ... (as trial_jobs, an interrupted run has every policy as far)."""
    if batch <= 0:
        return [[job] for job in jobs]
    per_policy: dict[str, list[TrialJob]] = {}
    for job in sorted(jobs, key=lambda j: j.index):
        per_policy.setdefault(job.policy, []).append(job)
    chunks = [[js[i:i + batch] for i in range(0, len(js), batch)] for js in per_policy.values()]
    return [c[k] for k in range(max(map(len, chunks), default=0)) for c in chunks if k < len(c)]


def _spent(seconds: dict[str, float], before: dict[str, float], share: int = 1) -> dict[str, float]:
    return {k: (seconds[k] - before.get(k, 0.0)) / share for k in seconds}


class TrialRunner:
    """One env (and, with `policy_eval.batch`, one batched env) and the policies it has loaded; runs one unit of
    trial_units at a time."""

    def __init__(self, params: dict[str, Any], videos_dir: Path) -> None:
        from wc.policy_eval.env import WorldContactLiftEnv

        self.env = WorldContactLiftEnv(params)
        self.videos_dir = Path(videos_dir)
        self.actors: dict[str, PolicyActor] = {}
        self.batched: BatchedLiftEnv | None = None  # built on the first batch

    def __call__(self, unit: list[TrialJob]) -> list[TrialResult]:
        return self._batch(unit) if self.env.cfg.batch else [self._trial(job) for job in unit]

    def _actor(self, job: TrialJob) -> tuple[PolicyActor, float]:
        """The job's policy as an actor, and the seconds loading it took (0 when loaded before)."""
        from wc.policy.finetune import load_policy
        from wc.policy_eval.closed_loop import PolicyActor

        load_s = 0.0
        if job.path not in self.actors:
            tic = time.perf_counter()
            self.actors[job.path] = PolicyActor(*load_policy(job.path, self.env.device), instruction=self.env.instruction)
            load_s = time.perf_counter() - tic
        return self.actors[job.path], load_s

    def _trial(self, job: TrialJob) -> TrialResult:
        from wc.policy_eval.closed_loop import run_episode

        actor, load_s = self._actor(job)
        before = dict(self.env.seconds)
        outcome, frames, s_per_step = run_episode(self.env, actor, job.seed, job.record)
        self._write_video(job, frames)
        return TrialResult(job, outcome.to_json(), s_per_step, _spent(self.env.seconds, before), load_s)

    def _batch(self, jobs: list[TrialJob]) -> list[TrialResult]:
        from wc.policy_eval.batched_env import BatchedLiftEnv
        from wc.policy_eval.closed_loop import run_batch

        if self.batched is None:
            self.batched = BatchedLiftEnv(self.env, min(self.env.cfg.batch, self.env.cfg.trials))
        actor, load_s = self._actor(jobs[0])
        before = dict(self.batched.seconds)  # its reset seconds include planning (the env's plans)
        outcomes, frames, s_per_step = run_batch(self.batched, actor, [j.seed for j in jobs], [j.record for j in jobs])
        for job, trial_frames in zip(jobs, frames):
            self._write_video(job, trial_frames)
        spent = _spent(self.batched.seconds, before, len(jobs))
        return [TrialResult(job, outcome.to_json(), s_per_step, spent, load_s if k == 0 else 0.0)
                for k, (job, outcome) in enumerate(zip(jobs, outcomes))]

    def _write_video(self, job: TrialJob, frames: list) -> None:
        from wc.policy_eval.videos import write_mp4

        if job.record:
            write_mp4(self.videos_dir / job.video_name, frames, self.env.metadata["render_fps"])


_RUNNER: TrialRunner | None = None  # the worker process's runner


def _start_worker(params: dict[str, Any], videos_dir: Path, torch_threads: int) -> None:
    import torch

    global _RUNNER
    torch.set_num_threads(torch_threads)
    _RUNNER = TrialRunner(params, videos_dir)


def _run_unit(unit: list[TrialJob]) -> list[TrialResult]:
    assert _RUNNER is not None, "worker not started"
    return _RUNNER(unit)


def run_trials(params: dict[str, Any], jobs: list[TrialJob], videos_dir: Path, workers: int,
               on_result: Callable[[TrialResult], None] | None = None) -> list[TrialResult]:
    """Run every job (in `workers` processes when > 1; `policy_eval.batch` trials at once when > 0); returns the
    results in job order."""
    position = {job: i for i, job in enumerate(jobs)}
    units = trial_units(jobs, load_section(params, "policy_eval", PolicyEvalConfig).batch)
    done: dict[int, TrialResult] = {}

    def collect(results: list[TrialResult]) -> None:
        for result in results:
            done[position[result.job]] = result
            if on_result is not None:
                on_result(result)

    if workers <= 1:
        runner = TrialRunner(params, videos_dir)
        for unit in units:
            collect(runner(unit))
        return [done[i] for i in range(len(jobs))]
    with spawn_pool(min(workers, len(units)), _start_worker, (params, videos_dir, cores_each(workers))) as pool:
        for future in as_completed([pool.submit(_run_unit, unit) for unit in units]):
            collect(future.result())
    return [done[i] for i in range(len(jobs))]


def by_policy(results: Iterable[TrialResult]) -> dict[str, list[TrialResult]]:
    """Results grouped per policy, in trial order."""
    grouped: dict[str, list[TrialResult]] = {}
    for r in sorted(results, key=lambda r: r.job.index):
        grouped.setdefault(r.job.policy, []).append(r)
    return grouped
