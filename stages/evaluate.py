"""Stage `evaluate`: held-out rollouts and long stability rollouts of WorldContact, the baselines, the
ablations and the zero-motion / constant-velocity references -> reports/metrics.json (DVC metrics),
reports/stability.csv and reports/stability.png (DVC plots).

    python -m stages.evaluate [--params params.yaml] [--set evaluate.stability_frames=150 ...]

The work is `wc.eval.stage.evaluate` (importable, used by the tests); see it for the rules.
"""

from wc.eval.stage import evaluate, evaluate_summary
from wc.paths import EVALUATE
from wc.stage_cli import StageCommand

COMMAND = StageCommand("evaluate", __doc__, evaluate, evaluate_summary, EVALUATE, keywords={"store": "store_path"})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
