"""Stage `validate`: physical checks of data/source/raw.zarr -> data/source/trajectories.zarr (accepted
episodes only, with their train / val / test split) and reports/validate.json.

    python -m stages.validate [--params params.yaml] [--set validate.penetration_tol_m=0.005 ...]

The work is `wc.validate.stage.validate` (importable, used by the tests); see it for the rules.
"""

from wc.paths import VALIDATE
from wc.stage_cli import StageCommand
from wc.validate.stage import NoAcceptedEpisodesError, validate, validate_summary

COMMAND = StageCommand("validate", __doc__, validate, validate_summary, VALIDATE, expected=(NoAcceptedEpisodesError,))
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
