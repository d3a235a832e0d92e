"""Stage `train_baselines`: RoboCraft, RoboCook, AdaptiGraph on data/source/trajectories.zarr
-> models/baselines/<name>/ and reports/train_baselines.json.

    python -m stages.train_baselines [--params params.yaml] [--set baselines.names=[robocook] ...]

Each baseline trains on the split and holdout rule of the `train` section (wc.baselines.train).
"""

from wc.baselines.baselines_stage import run, train_baselines_summary
from wc.paths import TRAIN_BASELINES
from wc.stage_cli import StageCommand

COMMAND = StageCommand("train_baselines", __doc__, run, train_baselines_summary, TRAIN_BASELINES)
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
