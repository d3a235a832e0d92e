"""Stage `policy_eval`: closed-loop evaluation of the trained policies (models/policy/{source,expanded}) in the
Newton simulator on the same trial seeds -> reports/policy.json, reports/policy_videos/,
reports/policy_success.{csv,json,png} (the json: per-arm DVC metrics).

    python -m stages.policy_eval [--params params.yaml] [--set policy_eval.trials=20 ...]

The work is `wc.policy_eval.stage.run` (importable, used by the tests); the environment is
wc.policy_eval.env.WorldContactLiftEnv, also a lerobot env plugin (package lerobot_env_worldcontact).
"""

from wc.paths import POLICY_EVAL
from wc.policy_eval.stage import policy_eval_summary, run
from wc.stage_cli import StageCommand

COMMAND = StageCommand("policy_eval", __doc__, run, policy_eval_summary, POLICY_EVAL, keywords={"videos": "videos_dir"})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
