"""Errors a user reads: a stage run from the command line ends an expected error with one line on stderr and
exit status 2, not a traceback (wc.cli); WC_TRACEBACK=1 brings the traceback back. The cases fail before any
simulation or training starts, so each run costs about one import of the stage."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.stage_run import assert_one_line_error, run_stage
from wc.cli import error_line, run_cli
from wc.config import ParamsError


@pytest.mark.slow
def test_validate_missing_input(tmp_path: Path) -> None:
    out = tmp_path / "out.zarr"
    done = run_stage("validate", "--raw", str(tmp_path / "absent.zarr"), "--out", str(out), "--report",
                     str(tmp_path / "r.json"))
    assert_one_line_error(done, "validate", "absent.zarr", "not found", "simulate stage first")
    assert not out.exists()


@pytest.mark.slow
def test_train_bad_override(tmp_path: Path) -> None:
    done = run_stage("train", "--set", "train.base.steps=many", "--store", str(tmp_path / "absent.zarr"), "--out",
                     str(tmp_path / "m"), "--report", str(tmp_path / "r.json"))
    assert_one_line_error(done, "train", "train.base.steps", "integer", "'many'")


@pytest.mark.slow
def test_params_file_not_yaml(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text("scene: [\n  a\nvalidate: 1\n")
    done = run_stage("validate", "--params", str(params), "--raw", str(tmp_path / "absent.zarr"))
    assert_one_line_error(done, "validate", str(params), "not valid YAML")


@pytest.mark.slow
def test_params_file_missing_and_traceback_on_request(tmp_path: Path) -> None:
    args = ("--params", str(tmp_path / "absent.yaml"), "--store", str(tmp_path / "absent.zarr"))
    assert_one_line_error(run_stage("train", *args), "train", "params file not found", "absent.yaml")
    done = run_stage("train", *args, traceback=True)
    assert done.returncode == 1
    assert "Traceback (most recent call last)" in done.stderr and "ParamsError: params file not found" in done.stderr


def _raise(err: BaseException) -> None:
    raise err


def test_run_cli_in_process(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WC_TRACEBACK", raising=False)
    err = ValueError("train: corrupt store\n  at ep_000001")
    err.add_note("while reading x")
    assert error_line("train", err) == "train: error: corrupt store at ep_000001; while reading x"
    with pytest.raises(SystemExit) as stop:
        run_cli(lambda: _raise(ParamsError("p.yaml: unknown key train.x")), "train")
    assert stop.value.code == 2 and capsys.readouterr().err == "train: error: p.yaml: unknown key train.x\n"
    with pytest.raises(SystemExit) as stop:
        run_cli(lambda: _raise(KeyboardInterrupt()), "simulate")
    assert stop.value.code == 130 and capsys.readouterr().err == "simulate: error: interrupted\n"
    with pytest.raises(SystemExit) as stop:  # a class the stage adds
        run_cli(lambda: _raise(LookupError("nothing accepted")), "validate", (LookupError,))
    assert stop.value.code == 2
    with pytest.raises(RuntimeError, match="a bug"):  # anything else: the traceback
        run_cli(lambda: _raise(RuntimeError("a bug")), "train")
    monkeypatch.setenv("WC_TRACEBACK", "1")
    with pytest.raises(ParamsError):
        run_cli(lambda: _raise(ParamsError("p.yaml: bad")), "train")
