"""Stage `dataset`: rendered frames + trajectories -> LeRobot v3 datasets data/lerobot/{source,expanded}
and reports/dataset.json.

    python -m stages.dataset [--params params.yaml] [--set dataset.include_expanded=false ...]

The work is `wc.policy.dataset_stage.build_datasets` (importable, used by the tests); the frame and
action alignment is documented in `wc.policy.dataset` and in each dataset's README.md.
"""

from wc.paths import DATASET
from wc.policy.dataset_stage import build_datasets, dataset_summary
from wc.stage_cli import StageCommand

COMMAND = StageCommand("dataset", __doc__, build_datasets, dataset_summary, DATASET,
                       helps={"out": "writes <out>/source and <out>/expanded"})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
