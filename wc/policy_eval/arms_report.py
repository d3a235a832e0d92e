"""The report of a policy comparison run with more than two arms, composed from its stage reports: per arm the
trials, successes, the 95 % Wilson interval, training episodes and failures; each arm's difference to the source
arm with Newcombe's interval (from the two Wilson intervals); the wall times that produced the extra trajectories
with Newton and with WorldContact, and the world model that generated them (path and params hash).

    python -m wc.policy_eval.arms_report RUN_DIR OUT_JSON [--extra 125]

RUN_DIR holds the run's stage reports: policy.json (policy_eval), finetune_<arm>.json (finetune, one per arm),
simulate.json and validate.json (the Newton data), expand.json (the WorldContact data). The three-arm comparison
(reports/gpu/policy_h100_three_arms.json) was composed from reports/gpu/policy_h100_three_arms/ this way.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from wc.cli import run_cli
from wc.policy_eval.success import wilson_interval
from wc.reports import write_json_atomic

RUN_REPORTS = ("policy.json", "simulate.json", "validate.json", "expand.json")
SCRIPTS = ["scripts/gpu/policy_comparison_data.sh", "scripts/gpu/policy_comparison_policies.sh"]


def newcombe_difference(k1: int, n1: int, k2: int, n2: int) -> tuple[float, float, float]:
    """p1 - p2 and its 95 % interval (Newcombe's method 10, from the two Wilson intervals)."""
    p1, p2 = k1 / n1, k2 / n2
    (l1, u1), (l2, u2) = wilson_interval(k1, n1), wilson_interval(k2, n2)
    d = p1 - p2
    return d, d - math.hypot(p1 - l1, u2 - p2), d + math.hypot(u1 - p1, p2 - l2)


def _read(run: Path, name: str) -> dict[str, Any]:
    path = run / name
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (a comparison run folder holds {', '.join(RUN_REPORTS)} and "
                                "finetune_<arm>.json per arm)")
    return json.loads(path.read_text())


def compose(run: Path, extra: int = 125) -> dict[str, Any]:
    """The comparison report of the run folder `run`; `extra`: trajectories each data-production method added to the
    source ones (the wall times are scaled to it)."""
    policy, sim, val, exp = (_read(run, name) for name in RUN_REPORTS)
    arms = {}
    for name, p in policy["policies"].items():
        train = _read(run, f"finetune_{name}.json")["datasets"][name]
        arms[name] = {"trials": p["trials"], "successes": p["successes"], "success_rate": p["success_rate"],
                      "ci95": p["ci95"], "episodes": p["episodes"], "frames": train["frames"],
                      "failures": p["failures"], "final_loss": train["final_loss"], "train_s": train["train_s"]}
    if "source" not in arms:
        raise ValueError(f"{run / 'policy.json'}: no 'source' arm to compare the others with (arms: {sorted(arms)})")
    src = arms["source"]
    for name, arm in arms.items():
        if name != "source":
            d, lo, hi = newcombe_difference(arm["successes"], arm["trials"], src["successes"], src["trials"])
            arm["minus_source"] = {"difference": d, "ci95": [lo, hi]}
    newton_s = sim["wall_s"] + val["wall_s"]
    return {
        "arms": arms, "task": policy["task"], "trial_seeds": policy["seeds"], "episode_seeds": policy["episode_seeds"],
        "lift_height_m": policy["lift_height_m"], "hold_s": policy["hold_s"], "policy_type": policy["policy_type"],
        "expanded_equals_source": policy["expanded_equals_source"],
        "data_production": {
            "newton": {"simulated": sim["episodes"], "accepted": val["accepted"], "simulate_s": sim["wall_s"],
                       "validate_s": val["wall_s"], "rejections": val["rejections"],
                       f"s_per_{extra}_accepted": newton_s * extra / val["accepted"]},
            "worldcontact": {"generated": exp["generated"], "accepted": exp["accepted"], "expand_s": exp["wall_s"],
                             "rollout_s": exp["rollout_s"], "rejections": exp["rejections"], "model": exp["model"]["path"],
                             "model_params_hash": exp["model"].get("params_hash"),
                             "model_step": exp["model"].get("step"),
                             f"s_per_{extra}_accepted": exp["wall_s"] * extra / exp["accepted"]},
        },
        "evaluation": {"wall_s": policy["timing"]["wall_s"], "workers": policy["timing"]["workers"],
                       "s_per_step": policy["timing"]["s_per_step"]},
        "environment": policy["timing"]["environment"],
        "sources": {"run": str(run), "scripts": SCRIPTS},
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m wc.policy_eval.arms_report", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the run folder of stage reports")
    parser.add_argument("out", type=Path, help="the comparison report to write (JSON)")
    parser.add_argument("--extra", type=int, default=125, help="trajectories each method added to the source ones")
    args = parser.parse_args(argv)
    report = compose(args.run, args.extra)
    write_json_atomic(args.out, report)
    for name, arm in report["arms"].items():
        diff = arm.get("minus_source")
        print(f"{name}: {arm['successes']}/{arm['trials']} CI {arm['ci95'][0]:.3f}-{arm['ci95'][1]:.3f}, "
              f"{arm['episodes']} episodes" + (f"; minus source {diff['difference']:+.2f} "
                                               f"({diff['ci95'][0]:+.3f}, {diff['ci95'][1]:+.3f})" if diff else ""))
    return report


if __name__ == "__main__":
    run_cli(main, "arms_report")
