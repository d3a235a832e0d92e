"""Atomic writes through temporary siblings, and the removal of temporaries a killed writer left behind.

Every writer in wc names its temporary after the target `<name>` and its own process id:

    .<name>.tmp-<pid>            .<name>.tmp-<pid><suffix>      files (`write_atomic`)
    <name>.tmp-<pid>-<hex>       .<name>.tmp-<pid>-<hex>        directories (stores, datasets, models, videos)
    <name>.tmp-old-<pid>-<hex>   .<name>.old-<pid>-<hex>        the previous output, moved aside while replacing it

A writer that is killed mid-run cannot remove its temporary; `remove_stale_temporaries(target)`, called where
each writer starts, removes those whose process is gone. The pid is only meaningful on this host: two hosts
writing to one shared directory at once are not supported.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
from collections.abc import Callable
from pathlib import Path


def temporary_pattern(path: Path) -> re.Pattern[str]:
    """Names of the temporaries of `path` (see the module docstring); group `pid` is the writer's process id."""
    name, suffix = re.escape(path.name), re.escape(path.suffix)
    return re.compile(rf"(?:\.?{name}\.tmp(?:-old)?|\.{name}\.old)-(?P<pid>\d+)(?:-[0-9a-f]+|{suffix})?")


def temporary_sibling(path: Path) -> Path:
    """A fresh hidden temporary directory name beside `path` (`.<name>.tmp-<pid>-<hex>`), which
    `remove_stale_temporaries(path)` removes once this process is gone."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")


def process_alive(pid: int) -> bool:
    """Whether process `pid` exists on this host (one we may not signal counts as alive)."""
    if pid <= 0:
        return True  # not a process id a writer embeds: never treat it as gone
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporaries of `path` (files or directories) whose writing process is gone; returns them.

    Temporaries of a live process (this one included) and every other file are left alone."""
    path = Path(path)
    pattern = temporary_pattern(path)
    try:
        siblings = list(os.scandir(path.parent))
    except (FileNotFoundError, NotADirectoryError):
        return []
    removed = []
    for entry in siblings:
        match = pattern.fullmatch(entry.name)
        if match is None or process_alive(int(match["pid"])):
            continue
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path, ignore_errors=True)
        else:
            Path(entry.path).unlink(missing_ok=True)
        removed.append(Path(entry.path))
    return removed


def write_atomic(path: str | Path, write: Callable[[Path], object], keep_suffix: bool = False) -> Path:
    """Call `write(tmp)` on the temporary sibling `.<name>.tmp-<pid>` (+ `path`'s suffix when `keep_suffix`, for
    writers that pick the format from it), then rename it to `path`: a reader never sees a half-written file.
    Creates the parent directory and first removes stale temporaries of `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}{path.suffix if keep_suffix else ''}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
