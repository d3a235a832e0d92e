"""Compose reports/gpu/policy_h100_three_arms.json from the issue-20 GPU run's stage reports (reports/gpu/issue20/):
per arm trials, successes, the 95 % Wilson interval, training episodes and failures; the differences to the source
arm with Newcombe's interval (from the two Wilson intervals); the wall times that produced the 125 extra
trajectories with Newton and with WorldContact on the same GPU.

    python scripts/gpu/issue20_report.py [RUN_DIR] [OUT_JSON]
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

from wc.policy_eval.success import wilson_interval
from wc.reports import write_json_atomic

EXTRA = 125  # trajectories each data-production method adds to the 25 source ones


def newcombe_difference(k1: int, n1: int, k2: int, n2: int) -> tuple[float, float, float]:
    """p1 - p2 and its 95 % interval (Newcombe's method 10, from the two Wilson intervals)."""
    p1, p2 = k1 / n1, k2 / n2
    (l1, u1), (l2, u2) = wilson_interval(k1, n1), wilson_interval(k2, n2)
    d = p1 - p2
    return d, d - math.hypot(p1 - l1, u2 - p2), d + math.hypot(u1 - p1, p2 - l2)


def compose(run: Path) -> dict[str, Any]:
    read = lambda name: json.loads((run / name).read_text())  # noqa: E731
    policy, sim, val, exp = read("policy.json"), read("simulate.json"), read("validate.json"), read("expand.json")
    arms = {}
    for name, p in policy["policies"].items():
        train = read(f"finetune_{name}.json")["datasets"][name]
        arms[name] = {"trials": p["trials"], "successes": p["successes"], "success_rate": p["success_rate"],
                      "ci95": p["ci95"], "episodes": p["episodes"], "frames": train["frames"],
                      "failures": p["failures"], "final_loss": train["final_loss"], "train_s": train["train_s"]}
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
                       f"s_per_{EXTRA}_accepted": newton_s * EXTRA / val["accepted"]},
            "worldcontact": {"generated": exp["generated"], "accepted": exp["accepted"], "expand_s": exp["wall_s"],
                             "rollout_s": exp["rollout_s"], "rejections": exp["rejections"], "model": exp["model"]["path"],
                             f"s_per_{EXTRA}_accepted": exp["wall_s"] * EXTRA / exp["accepted"]},
        },
        "evaluation": {"wall_s": policy["timing"]["wall_s"], "workers": policy["timing"]["workers"],
                       "s_per_step": policy["timing"]["s_per_step"]},
        "environment": policy["timing"]["environment"],
        "sources": {"run": str(run), "scripts": ["scripts/gpu/issue20_data.sh", "scripts/gpu/issue20_policies.sh"]},
    }


if __name__ == "__main__":
    run = Path(sys.argv[1] if len(sys.argv) > 1 else "reports/gpu/issue20")
    out = Path(sys.argv[2] if len(sys.argv) > 2 else "reports/gpu/policy_h100_three_arms.json")
    report = compose(run)
    write_json_atomic(out, report)
    for name, arm in report["arms"].items():
        extra = arm.get("minus_source")
        print(f"{name}: {arm['successes']}/{arm['trials']} CI {arm['ci95'][0]:.3f}-{arm['ci95'][1]:.3f}, "
              f"{arm['episodes']} episodes" + (f"; minus source {extra['difference']:+.2f} "
                                               f"({extra['ci95'][0]:+.3f}, {extra['ci95'][1]:+.3f})" if extra else ""))
    print(json.dumps(report["data_production"], indent=1))
