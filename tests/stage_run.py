"""Run a stage as a user does (`python -m stages.<name>` in a subprocess) and check how it ends on an expected
error: status 2 and one line `<stage>: error: ...` on stderr, no traceback (wc.cli); before it, only the progress
a stage had shown."""

from __future__ import annotations

import os
import subprocess
import sys

from tests.conftest import ROOT


def run_stage(module: str, *args: str, traceback: bool = False, timeout_s: float = 300) -> subprocess.CompletedProcess:
    """`python -m stages.<module> ARGS` from the repository root, offline; `traceback`: WC_TRACEBACK=1."""
    env = {k: v for k, v in os.environ.items() if k != "WC_TRACEBACK"} | {"HF_HUB_OFFLINE": "1"}
    if traceback:
        env["WC_TRACEBACK"] = "1"
    return subprocess.run([sys.executable, "-m", f"stages.{module}", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout_s)


def assert_one_line_error(done: subprocess.CompletedProcess, stage: str, *words: str, progress: bool = False) -> str:
    """`done` exited 2 and its stderr is one line `<stage>: error: ...` holding every one of `words` (`progress`: the
    last line, after the stage's progress output, with no other error line); returns the line."""
    assert done.returncode == 2, done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    lines = done.stderr.splitlines()
    errors = [line for line in lines if "error" in line.lower()]
    assert (len(lines) == 1 or progress) and errors == lines[-1:], done.stderr[-3000:]
    assert lines[-1].startswith(f"{stage}: error: ") and all(w in lines[-1] for w in words), lines[-1]
    return lines[-1]
