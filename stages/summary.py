"""Stage `summary`: the headline figures of the stage reports -> reports/headline.json (the DVC metrics file) and
reports/RESULTS.md (with the list of GPU reports).

    python -m stages.summary [--reports reports]

The work is `wc.summary.write_summary`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from wc.cli import run_cli
from wc.summary import write_summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reports", default="reports", help="folder of the stage reports")
    parser.add_argument("--headline", default="reports/headline.json")
    parser.add_argument("--results", default="reports/RESULTS.md")
    args = parser.parse_args(argv)
    figures = write_summary(Path(args.reports), Path(args.headline), Path(args.results))
    missing = [k for k, v in figures.items() if v is None]
    print(f"summary: {len(figures) - len(missing)} of {len(figures)} headline figures"
          f"{' (missing: ' + ', '.join(missing) + ')' if missing else ''} -> {args.headline}, {args.results}")


if __name__ == "__main__":
    run_cli(main, "summary")
