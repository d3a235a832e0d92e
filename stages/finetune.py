"""Stage `finetune`: one lerobot policy per LeRobot dataset (data/lerobot/{source,expanded}), identical
settings and seed -> models/policy/{source,expanded}/ and reports/finetune.json.

    python -m stages.finetune [--params params.yaml] [--set policy.steps=50 ...]
    python -m stages.finetune --params params/gpu.yaml --policy params/policy_pi05.yaml   # pi0.5 recipe
    python -m stages.finetune --params params/gpu.yaml --policy params/policy_act_gpu.yaml   # ACT, one GPU

`--policy FILE` takes the `policy` section from FILE instead (`--set policy.*` then applies to it).

The work is `wc.policy.finetune.finetune` (importable, used by the tests), which trains with lerobot's own
`lerobot-train` code in this process (one GPU or the CPU; for several GPUs run `lerobot-train` under
`accelerate launch` per dataset); params `policy` (wc.policy.policy_config) say which policy, which datasets
and the recipe.
"""

from wc.paths import FINETUNE
from wc.policy.finetune_stage import finetune_summary, run, stage_params
from wc.stage_cli import StageCommand

COMMAND = StageCommand(
    "finetune", __doc__, run, finetune_summary, FINETUNE,
    params=lambda args: stage_params(args.params, args.overrides, args.policy),
    params_options={"--policy": {"default": None, "metavar": "FILE", "help": "take the policy section from FILE"}})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
