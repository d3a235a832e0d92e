"""Stage `dataset`: rendered frames + trajectories -> LeRobot v3 datasets data/lerobot/{source,expanded}
and reports/dataset.json.

    python -m stages.dataset [--params params.yaml] [--set dataset.include_expanded=false ...]

The work is `wc.policy.dataset_stage.build_datasets` (importable, used by the tests); the frame and
action alignment is documented in `wc.policy.dataset` and in each dataset's README.md.
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params
from wc.policy.dataset_stage import build_datasets

__all__ = ["build_datasets", "main"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--source-trajectories", default="data/source/trajectories.zarr")
    parser.add_argument("--source-frames", default="data/rendered/source.zarr")
    parser.add_argument("--expanded-trajectories", default="data/expanded/trajectories.zarr")
    parser.add_argument("--expanded-frames", default="data/rendered/expanded.zarr")
    parser.add_argument("--out", default="data/lerobot", help="writes <out>/source and <out>/expanded")
    parser.add_argument("--report", default="reports/dataset.json")
    args = parser.parse_args(argv)
    result = build_datasets(read_params(args.params, args.overrides), args.source_trajectories, args.source_frames,
                            args.expanded_trajectories, args.expanded_frames, args.out, args.report)
    for name, d in result["datasets"].items():
        if d is not None:
            print(f"dataset {name}: {d['episodes']} episodes, {d['frames']} frames at {d['fps']} fps "
                  f"-> {d['path']} ({d['wall_s']:.1f} s)")
    print(f"dataset: {result['wall_s']:.1f} s")


if __name__ == "__main__":
    run_cli(main, "dataset")
