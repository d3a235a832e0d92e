"""Stage `render`: top and wrist RGB views of every trajectory -> data/rendered/{source,expanded}.zarr,
reports/render.json and reports/render_contact_sheet.png.

    python -m stages.render [--params params.yaml] [--set render.tasks=[lift_handle] ...]
    python -m stages.render --inputs data/source/trajectories.zarr --outs /tmp/source.zarr

Without --inputs it renders data/source/trajectories.zarr, and data/expanded/trajectories.zarr when it
exists. The work is `wc.render.stage.render` (importable, used by the tests).
"""

from wc.paths import RENDER
from wc.render.stage import pairs_problem, render_inputs, render_summary
from wc.distributed import UnitsFailed
from wc.stage_cli import StageCommand

COMMAND = StageCommand(
    "render", __doc__, render_inputs, render_summary, RENDER, check=lambda args: pairs_problem(args.inputs, args.outs),
    expected=(UnitsFailed,),
    options={"--inputs": {"nargs": "+", "help": "trajectory stores to render (default: source [+ expanded])"},
             "--outs": {"nargs": "+", "help": "rendered-frames stores, one per input"}})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
