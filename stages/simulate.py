"""Stage `simulate`: run the task programs in the Newton source simulator -> data/source/raw.zarr.

    python -m stages.simulate [--params params.yaml] [--set agent.episodes_per_task=4 ...]
"""

from wc.agent.simulate_stage import run, simulate_summary
from wc.paths import SIMULATE
from wc.distributed import UnitsFailed
from wc.stage_cli import StageCommand

COMMAND = StageCommand(
    "simulate", __doc__, run, simulate_summary, SIMULATE, optional=("memory",),
    expected=(UnitsFailed,),
    helps={"memory": "the agent's failure memory, read and appended to ('' for none)"},
    options={"--max-minutes": {"type": float, "default": 0.0, "help": "start no batch of episodes after this wall "
                                                                      "time (0: no limit); what ran is kept"}})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
