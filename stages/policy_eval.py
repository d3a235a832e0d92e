"""Stage `policy_eval`: closed-loop evaluation of the trained policies (models/policy/{source,expanded}) in the
Newton simulator on the same trial seeds -> reports/policy.json, reports/policy_videos/,
reports/policy_success.{csv,png}.

    python -m stages.policy_eval [--params params.yaml] [--set policy_eval.trials=20 ...]

The work is `wc.policy_eval.stage.run` (importable, used by the tests); the environment is
wc.policy_eval.env.WorldContactLiftEnv, also a lerobot env plugin (package lerobot_env_worldcontact).
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params
from wc.policy_eval.stage import run

__all__ = ["main", "run"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--models-root", default="models/policy")
    parser.add_argument("--report", default="reports/policy.json")
    parser.add_argument("--videos", default="reports/policy_videos")
    parser.add_argument("--table", default="reports/policy_success.csv")
    parser.add_argument("--plot", default="reports/policy_success.png")
    args = parser.parse_args(argv)
    r = run(read_params(args.params, args.overrides), args.models_root, args.report, args.videos, args.table,
            args.plot)
    rates = ", ".join(f"{n} {p['successes']}/{p['trials']}" for n, p in r["policies"].items())
    print(f"policy_eval: {r['task']} success {rates}; {r['timing']['wall_s']:.0f} s")


if __name__ == "__main__":
    run_cli(main, "policy_eval")
