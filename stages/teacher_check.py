"""Stage `teacher_check`: the generated episodes replayed in Newton (wc/expand/teacher.py) -> reports/teacher_check.json.

    python -m stages.teacher_check [--params params.yaml] [--store data/expanded/trajectories.zarr] [--limit N]
"""

from wc.expand import teacher
from wc.paths import TEACHER_CHECK
from wc.stage_cli import StageCommand

COMMAND = StageCommand(  # --help: the teacher check's own description
    "teacher_check", teacher.__doc__, teacher.run, teacher.teacher_check_summary, TEACHER_CHECK, optional=("rejected",),
    helps={"rejected": "the rejected generated episodes ('' for none: precision only)"},
    options={"--limit": {"type": int, "default": None, "help": "check the first N episodes of each store only"}})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
