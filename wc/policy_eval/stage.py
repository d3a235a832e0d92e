"""The policy_eval stage: every trained policy (models/policy/<policy.datasets>) runs the same `trials` seeded
closed-loop episodes of the lift task -> reports/policy.json (success counts and rates side by side,
per-trial outcomes), mp4 videos of the first `videos` trials per policy, a CSV + bar chart of the rates.

Same params -> same report, apart from the `timing` entry. Missing policy directories fail before any
episode runs.
"""

from __future__ import annotations

import os
import secrets
import shutil
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from wc.atomic import remove_stale_temporaries
from wc.config import load_section, params_hash
from wc.paths import POLICY_EVAL
from wc.policy.comparison import FLAG, expanded_equals_source, trained_episodes
from wc.policy.finetune import SUMMARY_FILE, load_policy
from wc.policy.policy_config import PolicyConfig
from wc.policy.pretrained import checkpoint_weights
from wc.policy_eval.config import PolicyEvalConfig
from wc.policy_eval.env import WorldContactLiftEnv
from wc.policy_eval.plots import plot_success_rates, write_success_table
from wc.policy_eval.closed_loop import PolicyActor, run_episode
from wc.policy_eval.videos import write_mp4
from wc.reports import environment_info, replace_dir, write_json_atomic

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


def _summary(outcomes: list[dict[str, Any]]) -> dict[str, Any]:
    successes = sum(o["success"] for o in outcomes)
    failures: dict[str, int] = {}
    for o in outcomes:
        if o["failure"]:
            failures[o["failure"]] = failures.get(o["failure"], 0) + 1
    return {"successes": successes, "trials": len(outcomes), "success_rate": successes / len(outcomes),
            "failures": dict(sorted(failures.items())), "outcomes": outcomes}


def run(params: dict[str, Any], models_root: str | Path = POLICY_EVAL["models_root"],
        report: str | Path = POLICY_EVAL["report"], videos_dir: str | Path = POLICY_EVAL["videos"],
        table: str | Path = POLICY_EVAL["table"], plot: str | Path = POLICY_EVAL["plot"],
        progress: bool = True) -> dict[str, Any]:
    """Evaluate each policy of `policy.datasets` on trial seeds policy_eval.seed + [0, trials); write the
    report, videos, table and plot. Returns the report."""
    cfg = load_section(params, "policy_eval", PolicyEvalConfig)
    policy_cfg = load_section(params, "policy", PolicyConfig)
    dirs = policy_dirs(models_root, policy_cfg.datasets)
    started = time.perf_counter()
    env = WorldContactLiftEnv(params)
    seeds = [cfg.seed + i for i in range(cfg.trials)]
    videos_dir = Path(videos_dir)
    videos_dir.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(videos_dir)
    tmp_videos = videos_dir.with_name(f".{videos_dir.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
    tmp_videos.mkdir()
    policies: dict[str, dict[str, Any]] = {}
    timing: dict[str, Any] = {"s_per_step": {}, "policy_load_s": {}}
    try:
        with tqdm(total=len(dirs) * cfg.trials, desc="policy_eval", unit="episode", disable=not progress) as bar:
            for name, path in dirs.items():
                tic = time.perf_counter()
                actor = PolicyActor(*load_policy(path, env.device), instruction=env.instruction)
                timing["policy_load_s"][name] = time.perf_counter() - tic
                outcomes, step_s = [], []
                for i, seed in enumerate(seeds):
                    record = i < cfg.videos
                    outcome, frames, s_per_step = run_episode(env, actor, seed, record)
                    if record:
                        video = f"{name}_trial{i:02d}_seed{seed}.mp4"
                        write_mp4(tmp_videos / video, frames, env.metadata["render_fps"])
                    outcomes.append(outcome.to_json() | ({"video": str(videos_dir / video)} if record else {}))
                    step_s.append(s_per_step)
                    bar.update()
                    bar.set_postfix({name: f"{sum(o['success'] for o in outcomes)}/{len(outcomes)}"})
                policies[name] = _summary(outcomes) | {"model": str(path)}
                timing["s_per_step"][name] = sum(step_s) / len(step_s)
        replace_dir(tmp_videos, videos_dir)
    finally:
        shutil.rmtree(tmp_videos, ignore_errors=True)
    equal = expanded_equals_source(trained_episodes(dirs, SUMMARY_FILE))
    write_success_table(table, policies)
    plot_success_rates(plot, policies, cfg.task, equal)
    timing |= {"wall_s": time.perf_counter() - started, "env_seconds": dict(env.seconds),
               "environment": environment_info(env.device)}
    result = {
        FLAG: equal, "task": cfg.task, "instruction": env.instruction, "policy_type": policy_cfg.type,
        "trials": cfg.trials, "seeds": seeds, "episode_seeds": [cfg.seed_offset + s for s in seeds],
        "lift_height_m": cfg.lift_height_m, "hold_s": cfg.hold_s, "max_steps": cfg.max_steps,
        "success_rate": {n: p["success_rate"] for n, p in policies.items()},
        "successes": {n: p["successes"] for n, p in policies.items()},
        "policies": policies, "videos": str(videos_dir), "table": str(table), "plot": str(plot),
        "params_hash": params_hash(params, SECTIONS), "device": env.device, "timing": timing,
    }
    write_json_atomic(report, result)
    return result


def policy_eval_summary(r: dict[str, Any]) -> str:
    """The line `python -m stages.policy_eval` prints."""
    rates = ", ".join(f"{n} {p['successes']}/{p['trials']}" for n, p in r["policies"].items())
    return f"policy_eval: {r['task']} success {rates}; {r['timing']['wall_s']:.0f} s"
