"""Stage `train`: WorldContact on data/source/trajectories.zarr -> models/worldcontact/ and reports/train.json.

    python -m stages.train [--params params.yaml] [--set train.base.steps=100 ...] [--resume]
    torchrun --nproc-per-node 8 -m stages.train --params params/gpu.yaml     # DistributedDataParallel
    python -m stages.train --set train.max_minutes=8 [--resume]              # a chunk of a long run: exit 75 = go on

A run cut by `train.max_minutes` (or `--stop-at-step`) leaves a complete checkpoint in `<out>.partial/` and exits
with status 75 (EX_TEMPFAIL); `--resume` continues it to the same result as one uninterrupted run.

Base stage, then the stage with the topology projection in the loop (wc.train.loop); the loss
curves go to reports/train_loss.{csv,png} (a DVC plot).
"""

from wc.paths import TRAIN
from wc.stage_cli import StageCommand
from wc.train.train_stage import run, train_exit_status, train_summary

COMMAND = StageCommand(
    "train", __doc__, run, train_summary, TRAIN, exit_status=train_exit_status,
    options={"--resume": {"action": "store_true", "help": "continue from <out>.partial/last_state.pt"},
             "--stop-at-step": {"type": int, "default": None, "help": "stop cleanly after this step (resumable)"}})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
