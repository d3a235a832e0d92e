"""`python -m wc.policy_eval.arms_report`: Newcombe's interval of a difference of two success rates, and the
committed three-arm comparison report is what the command writes from the committed run folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.conftest import ROOT
from wc.policy_eval.arms_report import compose, main, newcombe_difference

RUN = ROOT / "reports" / "gpu" / "policy_h100_three_arms"


def test_newcombe_interval_matches_the_published_example() -> None:
    """Newcombe (1998), Statistics in Medicine 17:873, Table II, method 10: 56/70 - 48/80 = 0.2000,
    95 % interval 0.0524 to 0.3339."""
    d, lo, hi = newcombe_difference(56, 70, 48, 80)
    assert d == pytest.approx(0.2) and lo == pytest.approx(0.0524, abs=5e-5) and hi == pytest.approx(0.3339, abs=5e-5)
    d, lo, hi = newcombe_difference(48, 80, 56, 70)  # the other way round: the interval mirrors
    assert d == pytest.approx(-0.2) and lo == pytest.approx(-0.3339, abs=5e-5) and hi == pytest.approx(-0.0524, abs=5e-5)


def test_the_committed_report_is_what_the_run_folder_composes(tmp_path: Path) -> None:
    out = tmp_path / "three_arms.json"
    main([str(RUN), str(out)])
    written, committed = json.loads(out.read_text()), json.loads((RUN.parent / f"{RUN.name}.json").read_text())
    written["sources"]["run"] = committed["sources"]["run"]  # the folder as given on the command line
    assert written == committed
    arms = written["arms"]
    assert [arms[a]["successes"] for a in ("source", "expanded", "newton_150")] == [37, 45, 48]
    assert written["data_production"]["worldcontact"]["model_params_hash"] == "3e36c8740e1d2286"


def test_a_missing_stage_report_is_named(tmp_path: Path) -> None:
    run = tmp_path / "run"
    shutil.copytree(RUN, run)
    (run / "finetune_expanded.json").unlink()
    with pytest.raises(FileNotFoundError, match="finetune_expanded.json: missing"):
        compose(run)
