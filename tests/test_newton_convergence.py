"""benchmarks.newton_convergence: the same specs at two iteration counts, Newton re-run against itself, the report,
table and chart written; each setting's verdicts compared with the most-iterated one's; bad arguments named."""

import json

import pytest

from benchmarks import newton_convergence
from tests.conftest import ROOT


@pytest.mark.slow
def test_two_iteration_counts_on_the_same_specs(tmp_path):
    out = tmp_path / "nc.json"
    newton_convergence.main(["--params", str(ROOT / "params.yaml"), "--set", "sim.worlds=2",
                             "--set", "tasks.bag_drop.duration_s=0.4", "--task", "bag_drop", "--iterations", "1,3",
                             "--plans", "2", "--perturb-m", "0", "0.003", "--out", str(out)])
    report = json.loads(out.read_text())
    low, high = report["settings"]
    assert (low["iterations"], high["iterations"]) == (1, 3) and low["plans"] == high["plans"] == 2
    for row in (low, high):
        rerun, noisy = row["self_agreement"]
        assert (rerun["perturb_m"], noisy["perturb_m"]) == (0.0, 0.003) and rerun["plans"] == 2
        assert sum(row["verdicts"].values()) == 2
        # another batch order moves a plan by float noise and VBD's unconverged colour order; 3 mm of noise further
        assert rerun["mean_rms_to_first_m"] < noisy["mean_rms_to_first_m"], row
        rejected = sum(n for verdict, n in row["verdicts"].items() if verdict != "accepted")
        assert sum(row["failures_by"].values()) <= rejected  # blow_up and penetration name their criterion or body
    assert "| 1 | 20 | 2 |" in out.with_suffix(".md").read_text() and out.with_suffix(".png").stat().st_size > 0


def test_agreement_is_with_the_most_iterated_setting_on_the_plans_both_ran():
    """Verdicts per spec seed planted for three settings, the most iterated not the last: a row's agreement is the
    share of the seeds both it and the most-iterated row planned whose verdicts agree (both accepted, or both
    rejected for whatever reason)."""
    rows = [{"iterations": 10}, {"iterations": 20}, {"iterations": 5}]
    verdicts = [{1: "accepted", 2: "blow_up", 3: "accepted"},
                {1: "accepted", 2: "penetration", 3: "not_lifted", 4: "accepted"},
                {1: "blow_up", 2: "accepted", 4: "accepted", 5: "accepted"}]  # seed 5 unplanned at 20
    newton_convergence.agreement_with_most_iterated(rows, verdicts)
    assert [r["most_iterated"] for r in rows] == [20, 20, 20]
    assert [r["agreement_with_most_iterated"] for r in rows] == pytest.approx([2 / 3, 1.0, 1 / 3])


def test_bad_arguments_are_named(capsys):
    with pytest.raises(SystemExit):
        newton_convergence.main(["--iterations", "5,0"])
    assert "positive integers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        newton_convergence.main(["--perturb-m", "-0.1"])
    assert "--perturb-m scales >= 0" in capsys.readouterr().err
