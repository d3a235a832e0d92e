"""Stage `teacher_check`: the generated episodes replayed in Newton (wc/expand/teacher.py) -> reports/teacher_check.json.

    python -m stages.teacher_check [--params params.yaml] [--store data/expanded/trajectories.zarr] [--limit N]
"""

from wc.cli import run_cli
from wc.expand.teacher import main

if __name__ == "__main__":
    run_cli(main, "teacher_check")
