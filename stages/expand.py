"""Stage `expand`: world-model trajectories of one task (params `expand`) -> data/expanded/trajectories.zarr
(accepted generated episodes only, `source: worldcontact`), data/expanded/rejected.zarr (the rejected ones, for
the teacher check) and reports/expand.json.

    python -m stages.expand [--params params.yaml] [--set expand.target_trajectories=10 ...]

The work is `wc.expand.stage.expand` (importable, used by the tests); see it for the rules.
"""

from wc.expand.stage import expand, expand_summary
from wc.paths import EXPAND
from wc.distributed import UnitsFailed
from wc.stage_cli import StageCommand

COMMAND = StageCommand(
    "expand", __doc__, expand, expand_summary, EXPAND, keywords={"model": "model_dir"}, optional=("rejected_out",),
    expected=(UnitsFailed,),
    helps={"model": "model folder (model.safetensors + model.json) or hf://owner/repo[/folder][@revision]",
           "rejected_out": "store of the rejected generated episodes, for the teacher check ('' to not keep them)"})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
