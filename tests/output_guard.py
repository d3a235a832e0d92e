"""A pytest plugin (registered by tests/conftest.py) that fails the run when a test wrote into the checkout's pipeline
outputs: everything under `data/`, `models/` and `reports/` is fingerprinted when the session starts and again when it
ends, and a file created, changed or deleted there sets a failing exit status and is named in the summary.

A fingerprint is a stat walk (os.scandir: size and mtime in ns per file), never a read, so a checkout holding large
Zarr stores costs a directory walk."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

GUARDED = ("data", "models", "reports")  # the checkout's DVC outputs and shipped reports

Fingerprint = dict[str, tuple[int, int]]  # path relative to the root, '/'-separated -> (size bytes, mtime ns)


def fingerprint(root: Path, folders: tuple[str, ...] = GUARDED) -> Fingerprint:
    """Size and mtime of every file (and symbolic link, not followed) under root/<folder> for each folder; an empty
    directory below them is listed too (as (-1, 0), its path ending in '/'), so creating one counts."""
    found: Fingerprint = {}
    tops = [root / f for f in folders]
    stack = list(tops)
    while stack:
        folder = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            continue
        if not entries and folder not in tops:
            found[folder.relative_to(root).as_posix() + "/"] = (-1, 0)
        for entry in entries:
            if entry.is_dir(follow_symlinks=False):
                stack.append(Path(entry.path))
            else:
                st = entry.stat(follow_symlinks=False)
                found[Path(entry.path).relative_to(root).as_posix()] = (st.st_size, st.st_mtime_ns)
    return found


def differences(before: Fingerprint, after: Fingerprint) -> list[str]:
    """'created <path>', 'changed <path>' or 'deleted <path>' per path that differs, sorted by path."""
    lines = []
    for path in sorted(before.keys() | after.keys()):
        if path not in before:
            lines.append(f"created {path}")
        elif path not in after:
            lines.append(f"deleted {path}")
        elif before[path] != after[path]:
            lines.append(f"changed {path}")
    return lines


class OutputGuard:
    """The plugin: the fingerprint of `root` at construction (the session's start), compared at the session's end."""

    SHOWN = 20  # paths named in the summary; the rest are counted

    def __init__(self, root: Path) -> None:
        self.root = root
        self.before = fingerprint(root)
        self.changed: list[str] = []

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        self.changed = differences(self.before, fingerprint(self.root))
        if self.changed and session.exitstatus == pytest.ExitCode.OK:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter: pytest.TerminalReporter) -> None:
        if not self.changed:
            return
        terminalreporter.section("the tests changed the checkout's pipeline outputs", sep="=", red=True, bold=True)
        terminalreporter.line(f"{len(self.changed)} path(s) under {', '.join(GUARDED)} of {self.root} changed during "
                              "the run (pass every output path of a stage or script into tmp_path):", red=True)
        for line in self.changed[:self.SHOWN]:
            terminalreporter.line(f"  {line}", red=True)
        if len(self.changed) > self.SHOWN:
            terminalreporter.line(f"  ... and {len(self.changed) - self.SHOWN} more", red=True)
