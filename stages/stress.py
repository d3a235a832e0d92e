"""Stage `stress`: stress cases (faster motion, heavier / lighter bag, unseen grasp, two objects, a held object
released mid-rollout) simulated in Newton (data/stress/trajectories.zarr) and rolled out by every evaluate
method -> reports/stress.csv, reports/stress.png, reports/stress_curves.csv, reports/stress.json, and a
side-by-side video (reports/stress_video.mp4 + reports/stress_side_by_side.png).

    python -m stages.stress [--params params.yaml] [--set stress.rollout_frames=100 ...]

The work is `wc.eval.stress.stress` (importable, used by the tests); see it for the rules.
"""

from wc.eval.stress import stress, stress_summary
from wc.paths import STRESS
from wc.stage_cli import StageCommand

COMMAND = StageCommand("stress", __doc__, stress, stress_summary, STRESS, keywords={"curves": "curves_csv"},
                       helps={"metrics": "evaluate's metrics: picks the baseline"})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
