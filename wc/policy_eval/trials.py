"""The closed-loop trials of every policy, in this process or spread over `policy_eval.workers` processes.

A trial depends only on its policy and seed (the env resets the physics, the actor its queue, torch its seed),
so trials can run in any process and order; the results come back sorted as the jobs were listed. Each worker
builds one env and loads each policy once, on its first trial of that policy. Workers are spawned and end with the
stage (wc.worker_pool). On one GPU the processes time-slice it: 12 workers on an H100 ran 150 trials only
~1.6x as fast as one process (reports/gpu/policy_h100_three_arms.md), so a few workers get most of the gain.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from concurrent.futures import as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from wc.worker_pool import spawn_pool

if TYPE_CHECKING:
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
    s_per_step: float
    env_seconds: dict[str, float]  # this trial's share of the env's reset / physics / render seconds
    load_s: float  # seconds loading the policy before this trial (0 when the process had it)


def trial_jobs(policies: dict[str, Path], seeds: list[int], videos: int) -> list[TrialJob]:
    """Trial-major: trial 0 of every policy, then trial 1, ... (an interrupted run has every policy as far)."""
    return [TrialJob(name, str(path), i, seed, i < videos) for i, seed in enumerate(seeds)
            for name, path in policies.items()]


class TrialRunner:
    """One env and the policies it has loaded; runs one job at a time."""

    def __init__(self, params: dict[str, Any], videos_dir: Path) -> None:
        from wc.policy_eval.env import WorldContactLiftEnv

        self.env = WorldContactLiftEnv(params)
        self.videos_dir = Path(videos_dir)
        self.actors: dict[str, PolicyActor] = {}

    def __call__(self, job: TrialJob) -> TrialResult:
        from wc.policy.finetune import load_policy
        from wc.policy_eval.closed_loop import PolicyActor, run_episode
        from wc.policy_eval.videos import write_mp4

        load_s = 0.0
        if job.path not in self.actors:
            tic = time.perf_counter()
            self.actors[job.path] = PolicyActor(*load_policy(job.path, self.env.device), instruction=self.env.instruction)
            load_s = time.perf_counter() - tic
        before = dict(self.env.seconds)
        outcome, frames, s_per_step = run_episode(self.env, self.actors[job.path], job.seed, job.record)
        if job.record:
            write_mp4(self.videos_dir / job.video_name, frames, self.env.metadata["render_fps"])
        spent = {k: self.env.seconds[k] - before.get(k, 0.0) for k in self.env.seconds}
        return TrialResult(job, outcome.to_json(), s_per_step, spent, load_s)


_RUNNER: TrialRunner | None = None  # the worker process's runner


def _start_worker(params: dict[str, Any], videos_dir: Path, torch_threads: int) -> None:
    import torch

    global _RUNNER
    torch.set_num_threads(torch_threads)
    _RUNNER = TrialRunner(params, videos_dir)


def _run_job(job: TrialJob) -> TrialResult:
    assert _RUNNER is not None, "worker not started"
    return _RUNNER(job)


def run_trials(params: dict[str, Any], jobs: list[TrialJob], videos_dir: Path, workers: int,
               on_result: Callable[[TrialResult], None] | None = None) -> list[TrialResult]:
    """Run every job (in `workers` processes when > 1); returns the results in job order."""
    done: dict[int, TrialResult] = {}

    def collect(i: int, result: TrialResult) -> None:
        done[i] = result
        if on_result is not None:
            on_result(result)

    if workers <= 1:
        runner = TrialRunner(params, videos_dir)
        for i, job in enumerate(jobs):
            collect(i, runner(job))
        return [done[i] for i in range(len(jobs))]
    threads = max(1, (os.cpu_count() or 1) // workers)
    with spawn_pool(min(workers, len(jobs)), _start_worker, (params, videos_dir, threads)) as pool:
        futures = {pool.submit(_run_job, job): i for i, job in enumerate(jobs)}
        for future in as_completed(futures):
            collect(futures[future], future.result())
    return [done[i] for i in range(len(jobs))]


def by_policy(results: Iterable[TrialResult]) -> dict[str, list[TrialResult]]:
    """Results grouped per policy, in trial order."""
    grouped: dict[str, list[TrialResult]] = {}
    for r in sorted(results, key=lambda r: r.job.index):
        grouped.setdefault(r.job.policy, []).append(r)
    return grouped
