"""Stage `stress`: stress cases (faster motion, heavier / lighter bag, unseen grasp, two objects, a held object
released mid-rollout) simulated in Newton (data/stress/trajectories.zarr) and rolled out by every evaluate
method -> reports/stress.csv, reports/stress.png, reports/stress_curves.csv, reports/stress.json, and a
side-by-side video (reports/stress_video.mp4 + reports/stress_side_by_side.png).

    python -m stages.stress [--params params.yaml] [--set stress.rollout_frames=100 ...]

The work is `wc.eval.stress.stress` (importable, used by the tests); see it for the rules.
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params
from wc.eval.stress import stress

__all__ = ["main", "stress"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--store", default="data/stress/trajectories.zarr")
    parser.add_argument("--metrics", default="reports/metrics.json", help="evaluate's metrics: picks the baseline")
    parser.add_argument("--csv", default="reports/stress.csv")
    parser.add_argument("--png", default="reports/stress.png")
    parser.add_argument("--curves", default="reports/stress_curves.csv")
    parser.add_argument("--report", default="reports/stress.json")
    parser.add_argument("--video", default="reports/stress_video.mp4")
    parser.add_argument("--sheet", default="reports/stress_side_by_side.png")
    args = parser.parse_args(argv)
    r = stress(read_params(args.params, args.overrides), args.store, args.csv, args.png, args.curves, args.report,
               args.video, args.sheet, args.metrics)

    def fmt(value: float | None, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    truth = r["ground_truth"]
    print(f"stress: {len(r['episodes'])} ground-truth episodes "
          f"({'reused' if truth['reused'] else 'simulated'}), {r['wall_s']['total']:.0f} s")
    for row in r["table"]:
        print(f"  {row['case']:20s} {row['method']:28s} x MSE {fmt(row['position_mse_m2'], '.3e')} m²  "
              f"vs CV {fmt(row['position_mse_vs_constant_velocity'], '.2f')}  "
              f"penetration {fmt(row['penetration_rate_pct'], '.2f')} %  strain {fmt(row['max_edge_strain'], '.2f')}  "
              f"diverged at {fmt(row['divergence_step'], 'd')}")
    print(f"  video: {r['video']['video']} ({r['video']['frames']} frames: {', '.join(r['video']['panels'])})")


if __name__ == "__main__":
    run_cli(main, "stress")
