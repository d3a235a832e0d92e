"""Stage `evaluate`: held-out rollouts and long stability rollouts of WorldContact, the baselines, the
ablations and the zero-motion / constant-velocity references -> reports/metrics.json (DVC metrics),
reports/stability.csv and reports/stability.png (DVC plots).

    python -m stages.evaluate [--params params.yaml] [--set evaluate.stability_frames=150 ...]

The work is `wc.eval.stage.evaluate` (importable, used by the tests); see it for the rules.
"""

from __future__ import annotations

import argparse

from wc.cli import run_cli
from wc.config import add_params_arguments, read_params
from wc.eval.stage import evaluate

__all__ = ["evaluate", "main"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--metrics", default="reports/metrics.json")
    parser.add_argument("--stability-csv", default="reports/stability.csv")
    parser.add_argument("--stability-png", default="reports/stability.png")
    args = parser.parse_args(argv)
    r = evaluate(read_params(args.params, args.overrides), args.store, args.metrics, args.stability_csv,
                 args.stability_png)

    def fmt(value: float | None, spec: str) -> str:
        return "diverged" if value is None else format(value, spec)

    print(f"evaluate: {r['held_out']['rollouts']} held-out rollouts ({r['held_out']['source']}), "
          f"{r['wall_s']:.0f} s")
    for name, m in r["methods"].items():
        div = r["stability"]["methods"].get(name, {})
        print(f"  {name:28s} x MSE {fmt(m['position_mse_m2'], '.3e')} m²  v MSE {fmt(m['velocity_mse_m2_s2'], '.3e')} "
              f"m²/s²  penetration {fmt(m.get('penetration_rate_pct'), '.2f')} % "
              f"(contact {fmt(m.get('contact_penetration_rate_pct'), '.2f')} %)  "
              f"diverged {div.get('diverged', 0)}/{div.get('rollouts', 0)} long rollouts")
    for name, why in r["skipped"].items():
        print(f"  {name:28s} skipped: {why}")


if __name__ == "__main__":
    run_cli(main, "evaluate")
