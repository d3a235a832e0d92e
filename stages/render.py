"""Stage `render`: top and wrist RGB views of every trajectory -> data/rendered/{source,expanded}.zarr,
reports/render.json and reports/render_contact_sheet.png.

    python -m stages.render [--params params.yaml] [--set render.tasks=[lift_handle] ...]
    python -m stages.render --inputs data/source/trajectories.zarr --outs /tmp/source.zarr

Without --inputs it renders data/source/trajectories.zarr, and data/expanded/trajectories.zarr when it
exists. The work is `wc.render.stage.render` (importable, used by the tests).
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params
from wc.render.stage import render

__all__ = ["main", "render"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--inputs", nargs="+", help="trajectory stores to render (default: source [+ expanded])")
    parser.add_argument("--outs", nargs="+", help="rendered-frames stores, one per input")
    parser.add_argument("--report", default="reports/render.json")
    parser.add_argument("--sheet", default="reports/render_contact_sheet.png")
    args = parser.parse_args(argv)
    if (args.inputs is None) != (args.outs is None) or (args.inputs and len(args.inputs) != len(args.outs)):
        parser.error("--inputs and --outs go together, one output per input")
    pairs = list(zip(args.inputs, args.outs)) if args.inputs else None
    result = render(read_params(args.params, args.overrides), pairs, args.report, args.sheet)
    speed = ", ".join(f"{n} {ms:.1f} ms" for n, ms in result["ms_per_frame"].items())
    print(f"render: {result['episodes']} episodes, {result['frames']} frames at {result['width']}x{result['height']} "
          f"on {result['device']} ({speed} per frame); {result['wall_s']:.1f} s; sheet {result['contact_sheet']}")


if __name__ == "__main__":
    run_cli(main, "render")
