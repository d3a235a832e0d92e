"""Stage `expand`: world-model trajectories of one task (params `expand`) -> data/expanded/trajectories.zarr
(accepted generated episodes only, `source: worldcontact`), data/expanded/rejected.zarr (the rejected ones, for
the teacher check) and reports/expand.json.

    python -m stages.expand [--params params.yaml] [--set expand.target_trajectories=10 ...]

The work is `wc.expand.stage.expand` (importable, used by the tests); see it for the rules.
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params
from wc.expand.stage import expand

__all__ = ["expand", "main"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--model", default="models/worldcontact", help="checkpoint dir (model.safetensors + .json)")
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--out", default="data/expanded/trajectories.zarr")
    parser.add_argument("--report", default="reports/expand.json")
    parser.add_argument("--rejected-out", default="data/expanded/rejected.zarr",
                        help="store of the rejected generated episodes, for the teacher check ('' to not keep them)")
    args = parser.parse_args(argv)
    r = expand(read_params(args.params, args.overrides), args.model, args.store, args.out, args.report,
               args.rejected_out or None)
    failed = ", ".join(f"{k} {v}" for k, v in r["rejections"].items() if v) or "none"
    print(f"expand {r['task']}: {r['accepted']}/{r['generated']} generated episodes accepted "
          f"({r['infeasible_plans']} plans infeasible); rejected: {failed}; {r['expanded_total']}/"
          f"{r['target_trajectories']} trajectories with the {r['source_episodes']} source ones"
          f"{'' if r['target_reached'] else ' (target NOT reached)'}; {r['trajectories_per_min']:.2f} generated/min "
          f"on {r['device']}, {r['wall_s']:.1f} s")


if __name__ == "__main__":
    run_cli(main, "expand")
