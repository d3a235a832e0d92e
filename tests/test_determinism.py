"""wc.determinism: WC_DETERMINISTIC reaches warp kernel modules defined after wc.warp_settings (their atomics in a
fixed order) and torch, is recorded beside timings, and a bad value fails naming the variable. Each case runs in a
fresh process, since the setting applies at import."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT

PROBE = """\
import wc.warp_settings  # noqa: F401  (first, as in every module that defines kernels)
import torch
import warp as wp

from wc.reports import environment_info


@wp.kernel
def total(values: wp.array(dtype=float), out: wp.array(dtype=float)):
    wp.atomic_add(out, 0, values[wp.tid()])


values = wp.full(1000, 0.1, dtype=float, device="cpu")
out = wp.zeros(1, dtype=float, device="cpu")
wp.launch(total, values.shape[0], inputs=[values, out], device="cpu")
print(int(wp.get_module(total.__module__).options["deterministic"]), torch.are_deterministic_algorithms_enabled(),
      environment_info("cpu")["deterministic"], round(float(out.numpy()[0]), 2))
"""


def _probe(tmp_path: Path, mode: str | None) -> subprocess.CompletedProcess:
    (tmp_path / "probe_kernels.py").write_text(PROBE)  # warp reads a kernel's source from its file
    env = {k: v for k, v in os.environ.items() if k != "WC_DETERMINISTIC"}
    if mode is not None:
        env["WC_DETERMINISTIC"] = mode
    env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{tmp_path}"
    return subprocess.run([sys.executable, "-c", "import probe_kernels"], env=env, capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)


@pytest.mark.parametrize("mode, expected", [(None, "0 False off 100.0"), ("off", "0 False off 100.0"),
                                            ("run_to_run", "1 True run_to_run 100.0"),
                                            ("GPU_to_GPU", "2 True gpu_to_gpu 100.0")])
def test_the_mode_reaches_kernels_torch_and_the_report(tmp_path: Path, mode: str | None, expected: str) -> None:
    run = _probe(tmp_path, mode)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip().splitlines()[-1] == expected


def test_a_bad_mode_names_the_variable_and_the_choices(tmp_path: Path) -> None:
    run = _probe(tmp_path, "always")
    assert run.returncode != 0
    assert "WC_DETERMINISTIC='always': expected one of off, run_to_run, gpu_to_gpu" in run.stderr
