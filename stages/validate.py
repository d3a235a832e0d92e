"""Stage `validate`: physical checks of data/source/raw.zarr -> data/source/trajectories.zarr (accepted
episodes only, with their train / val / test split) and reports/validate.json.

    python -m stages.validate [--params params.yaml] [--set validate.penetration_tol_m=0.005 ...]

The work is `wc.validate.stage.validate` (importable, used by the tests); see it for the rules.
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params
from wc.validate.stage import NoAcceptedEpisodesError, validate

__all__ = ["main", "validate"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--raw", default="data/source/raw.zarr")
    parser.add_argument("--out", default="data/source/trajectories.zarr")
    parser.add_argument("--report", default="reports/validate.json")
    args = parser.parse_args(argv)
    result = validate(read_params(args.params, args.overrides), args.raw, args.out, args.report)
    failed = ", ".join(f"{k} {v}" for k, v in result["rejections"].items() if v) or "none"
    print(f"validate: {result['accepted']}/{result['episodes']} episodes accepted "
          f"(train {result['splits']['train']}, val {result['splits']['val']}, test {result['splits']['test']}); "
          f"rejected: {failed}; {result['wall_s']:.1f} s")


if __name__ == "__main__":
    run_cli(main, "validate", (NoAcceptedEpisodesError,))
