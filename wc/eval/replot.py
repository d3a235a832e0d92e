"""The long-rollout stability figure drawn again from a stability CSV (a run's reports/stability.csv, or one a GPU job
sent back without its PNG):

    python -m wc.eval.replot reports/gpu/lift_expansion/heldout_stability_final.csv out.png [--strain-bound 2.0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from wc.eval.plots import plot_stability
from wc.eval.stability import read_csv_curves


def replot(csv_path: str | Path, png_path: str | Path, strain_bound: float | None = None) -> Path:
    """Write the three-panel stability figure of `csv_path`'s curves to `png_path`."""
    curves, dt = read_csv_curves(csv_path)
    return plot_stability(curves, png_path, dt, strain_bound=strain_bound)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("csv", type=Path, help="stability CSV (evaluate's --stability-csv)")
    parser.add_argument("png", type=Path, help="figure to write")
    parser.add_argument("--strain-bound", type=float, default=None, help="divergence strain bound to draw (dashed)")
    args = parser.parse_args(argv)
    if not args.csv.is_file():
        parser.error(f"stability CSV {args.csv} not found")
    print(replot(args.csv, args.png, args.strain_bound))


if __name__ == "__main__":
    main()
