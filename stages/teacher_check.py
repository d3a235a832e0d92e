"""Stage `teacher_check`: the generated episodes replayed in Newton (wc/expand/teacher.py) -> reports/teacher_check.json.

    python -m stages.teacher_check [--params params.yaml] [--store data/expanded/trajectories.zarr] [--limit N]
        [--newton-perturb-m S [S ...]]
"""

from wc.expand import teacher
from wc.paths import TEACHER_CHECK
from wc.stage_cli import StageCommand

COMMAND = StageCommand(  # --help: the teacher check's own description
    "teacher_check", teacher.__doc__, teacher.run, teacher.teacher_check_summary, TEACHER_CHECK, optional=("rejected",),
    helps={"rejected": "the rejected generated episodes ('' for none: precision only)"},
    options={"--limit": {"type": int, "default": None, "help": "check the first N episodes of each store only"},
             "--newton-perturb-m": {"type": float, "nargs": "*", "default": None,
                                    "help": "Newton against itself: replay every plan again per scale, in another "
                                            "batch order, frame-0 positions + N(0, scale^2) [m] (0: re-run only)"}})
main = COMMAND.main

if __name__ == "__main__":
    COMMAND.cli()
