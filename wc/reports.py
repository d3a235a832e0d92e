"""Stage reports: JSON, CSV and figures written atomically (temporary sibling, then rename; see wc.atomic)."""

from __future__ import annotations

import csv
import json
import os
import platform
import secrets
import shutil
from pathlib import Path
from collections.abc import Iterable
from typing import Any

from wc.atomic import write_atomic


def cell(value: Any, fmt: str = ".1f", scale: float = 1.0) -> str:
    """A report table's cell: value x scale formatted, "-" for a missing value."""
    return "-" if value is None else format(scale * value, fmt)


def write_json_atomic(path: str | Path, data: dict[str, Any]) -> Path:
    """Write `data` as indented JSON at `path`; a reader never sees a half-written file."""
    text = json.dumps(data, indent=2, sort_keys=True, default=float) + "\n"
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def write_report_atomic(path: str | Path, data: dict[str, Any], table: str) -> Path:
    """A benchmark's report: `data` as JSON at `path` and `table` (its markdown) beside it as `.md`, each atomically."""
    path = write_json_atomic(path, data)
    write_atomic(path.with_suffix(".md"), lambda tmp: tmp.write_text(table))
    return path


def host_environment(device: str, gpus: int) -> dict[str, str]:
    """environment_info of a run spread over this host's `gpus` GPUs: `gpu` reads e.g. "2 x NVIDIA H200"."""
    info = environment_info("cuda:0" if gpus else device)
    if gpus:
        info.update(device=device, gpu=f"{gpus} x {info['gpu']}")
    return info


def environment_info(device: str) -> dict[str, str]:
    """Device and library versions, recorded beside every timing."""
    import torch
    import warp

    from wc.determinism import active_mode

    try:
        import newton
        newton_version = newton.__version__
    except ImportError:  # a training-only machine needs no simulator
        newton_version = "not installed"
    info = {"device": device, "python": platform.python_version(), "torch": torch.__version__,
            "warp": warp.__version__, "newton": newton_version, "cpu": platform.processor() or platform.machine(),
            "cpu_count": str(os.cpu_count())}
    info["deterministic"] = active_mode()  # warp's atomics ordering (WC_DETERMINISTIC)
    if device.startswith("cuda"):
        info["gpu"] = warp.get_device(device).name
    return info


def write_csv_atomic(path: str | Path, header: list[str], rows: Iterable[Iterable[Any]]) -> Path:
    """Write a CSV table at `path` atomically."""

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(header)
            writer.writerows(rows)

    return write_atomic(path, write)


def save_figure_atomic(fig: Any, path: str | Path) -> Path:
    """Save a matplotlib figure at `path` atomically and close it."""
    import matplotlib.pyplot as plt

    try:
        return write_atomic(path, fig.savefig, keep_suffix=True)
    finally:
        plt.close(fig)


def pyplot() -> Any:
    """matplotlib.pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def replace_dir(tmp: str | Path, path: str | Path) -> None:
    """Rename the finished directory `tmp` to `path`, swapping out what was there; on failure the old one stays.

    Callers check first that `path` is theirs to replace (e.g. a dataset or a saved model).
    """
    tmp, path = Path(tmp), Path(path)
    old = path.with_name(f".{path.name}.old-{os.getpid()}-{secrets.token_hex(4)}") if path.exists() else None
    if old is not None:
        os.rename(path, old)
    try:
        os.rename(tmp, path)
    except BaseException:
        if old is not None:
            os.rename(old, path)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
