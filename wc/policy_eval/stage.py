"""The policy_eval stage: every trained policy (models/policy/<policy.datasets>) runs the same `trials` seeded
closed-loop episodes of the lift task -> reports/policy.json (success counts and rates side by side,
95 % Wilson intervals, per-trial outcomes), mp4 videos of the first `videos` trials per policy, a CSV + bar chart of the rates
and reports/policy_success.json (per arm: successes, trials, rate, interval; DVC metrics).

Same params -> same report, apart from the `timing` entry, with any number of `policy_eval.workers` (trials run in
worker processes, wc.policy_eval.trials). `policy_eval.batch` N > 0 runs N trials of a policy at once as the worlds
of one Newton model (wc.policy_eval.batched_env): a report of the same shape, the same initial states per trial
seed, physics equal up to the solver's order of work (see there); timing.batch records it. Missing policy
directories fail before any episode runs.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from wc.atomic import remove_stale_temporaries, temporary_sibling
from wc.config import load_section, params_hash
from wc.devices import resolve_warp_device
from wc.model_ref import file_sha256
from wc.paths import POLICY_EVAL
from wc.policy.comparison import FLAG, SUMMARY_FILE, expanded_equals_source, trained_episodes
from wc.policy.policy_config import PolicyConfig
from wc.policy.pretrained import checkpoint_weights
from wc.policy_eval.config import PolicyEvalConfig
from wc.policy_eval.plots import plot_success_rates, write_success_metrics, write_success_table
from wc.policy_eval.success import wilson_interval
from wc.policy_eval.trials import TrialResult, by_policy, run_trials, trial_jobs
from wc.reports import environment_info, replace_dir, write_json_atomic
from wc.smoke import smoke_label

SECTIONS = ["policy_eval", "policy", "scene", "sim", "render", "tasks", "dataset"]


def policy_dirs(models_root: str | Path, names: list[str] | tuple[str, ...]) -> dict[str, Path]:
    """models_root/<name> per policy, each checked to hold a saved policy (clear error otherwise)."""
    dirs = {name: Path(models_root) / name for name in names}
    for name, path in dirs.items():
        if not path.is_dir():
            raise FileNotFoundError(f"policy_eval: no trained policy {name!r} at {path} (run the finetune stage "
                                    f"first; policy.datasets lists {list(names)})")
        checkpoint_weights(path, f"policy {name!r}")
    return dirs


def _summary(outcomes: list[dict[str, Any]], episodes: int | None) -> dict[str, Any]:
    successes = sum(o["success"] for o in outcomes)
    failures: dict[str, int] = {}
    for o in outcomes:
        if o["failure"]:
            failures[o["failure"]] = failures.get(o["failure"], 0) + 1
    return {"successes": successes, "trials": len(outcomes), "success_rate": successes / len(outcomes),
            "ci95": list(wilson_interval(successes, len(outcomes))), "episodes": episodes,
            "failures": dict(sorted(failures.items())), "outcomes": outcomes}


def run(params: dict[str, Any], models_root: str | Path = POLICY_EVAL["models_root"],
        report: str | Path = POLICY_EVAL["report"], videos_dir: str | Path = POLICY_EVAL["videos"],
        table: str | Path = POLICY_EVAL["table"], metrics: str | Path = POLICY_EVAL["metrics"],
        plot: str | Path = POLICY_EVAL["plot"], progress: bool = True) -> dict[str, Any]:
    """Evaluate each policy of `policy.datasets` on trial seeds policy_eval.seed + [0, trials) (in
    `policy_eval.workers` processes); write the report, videos, table, per-arm metrics and plot. Returns the report."""
    cfg = load_section(params, "policy_eval", PolicyEvalConfig)
    policy_cfg = load_section(params, "policy", PolicyConfig)
    dirs = policy_dirs(models_root, policy_cfg.datasets)
    device = resolve_warp_device(cfg.device, "policy_eval.device")
    started = time.perf_counter()
    seeds = [cfg.seed + i for i in range(cfg.trials)]
    videos_dir = Path(videos_dir)
    videos_dir.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(videos_dir)
    tmp_videos = temporary_sibling(videos_dir)
    tmp_videos.mkdir()
    try:
        with tqdm(total=len(dirs) * cfg.trials, desc="policy_eval", unit="episode", disable=not progress) as bar:
            wins = dict.fromkeys(dirs, 0)

            def tick(r: TrialResult) -> None:
                wins[r.job.policy] += r.outcome["success"]
                bar.update()
                bar.set_postfix(wins)

            results = run_trials(params, trial_jobs(dirs, seeds, cfg.videos), tmp_videos, cfg.workers, tick)
        replace_dir(tmp_videos, videos_dir)
    finally:
        shutil.rmtree(tmp_videos, ignore_errors=True)
    episodes = trained_episodes(dirs, SUMMARY_FILE)
    policies: dict[str, dict[str, Any]] = {}
    timing: dict[str, Any] = {"s_per_step": {}, "policy_load_s": {}, "env_seconds": {}}
    for name, trials in by_policy(results).items():
        outcomes = [r.outcome | ({"video": str(videos_dir / r.job.video_name)} if r.job.record else {}) for r in trials]
        policies[name] = _summary(outcomes, episodes[name]) | {
            "model": str(dirs[name]), "model_sha256": file_sha256(checkpoint_weights(dirs[name], f"policy {name!r}"))}
        timing["s_per_step"][name] = sum(r.s_per_step for r in trials) / len(trials)
        timing["policy_load_s"][name] = max(r.load_s for r in trials)
        for r in trials:
            for key, seconds in r.env_seconds.items():
                timing["env_seconds"][key] = timing["env_seconds"].get(key, 0.0) + seconds
    equal = expanded_equals_source(episodes)
    write_success_table(table, policies)
    write_success_metrics(metrics, policies)
    plot_success_rates(plot, policies, cfg.task, equal)
    timing |= {"wall_s": time.perf_counter() - started, "workers": cfg.workers, "batch": cfg.batch,
               "environment": environment_info(device)}
    result = {
        FLAG: equal, "task": cfg.task, "instruction": policy_cfg.task, "policy_type": policy_cfg.type,
        "trials": cfg.trials, "seeds": seeds, "episode_seeds": [cfg.seed_offset + s for s in seeds],
        "lift_height_m": cfg.lift_height_m, "hold_s": cfg.hold_s, "max_steps": cfg.max_steps,
        "success_rate": {n: p["success_rate"] for n, p in policies.items()},
        "successes": {n: p["successes"] for n, p in policies.items()},
        "policies": policies, "videos": str(videos_dir), "table": str(table), "metrics": str(metrics),
        "plot": str(plot),
        "params_hash": params_hash(params, SECTIONS), "device": device, "timing": timing,
        **smoke_label(params, "policy_eval"),
    }
    write_json_atomic(report, result)
    return result


def policy_eval_summary(r: dict[str, Any]) -> str:
    """The line `python -m stages.policy_eval` prints."""
    rates = ", ".join(f"{n} {p['successes']}/{p['trials']}" for n, p in r["policies"].items())
    return f"policy_eval: {r['task']} success {rates}; {r['timing']['wall_s']:.0f} s"
