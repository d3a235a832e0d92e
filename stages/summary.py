"""Stage `summary`: the headline figures of the stage reports -> reports/headline.json (the DVC metrics file) and
reports/RESULTS.md (the GPU runs' headline figures first, each read from the fields its report kind declares in
wc/report_kinds.py; then these figures, labelled a smoke run when the policy evaluation ran too few trials).

    python -m stages.summary [--reports reports]

The work is `wc.summary.write_summary`.
"""

from wc.paths import SUMMARY
from wc.stage_cli import StageCommand
from wc.summary import run, summary_line

COMMAND = StageCommand("summary", __doc__, run, summary_line, SUMMARY, params=None,
                       helps={"reports": "folder of the stage reports"})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
