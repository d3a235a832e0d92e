"""benchmarks.newton_convergence: the same specs at two iteration counts, Newton re-run against itself, the report,
table and chart written; bad arguments named."""

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
        assert 0.0 <= rerun["agreement"] <= 1.0 and sum(row["verdicts"].values()) == 2
        # another batch order moves a plan by float noise and VBD's unconverged colour order; 3 mm of noise further
        assert rerun["mean_rms_to_first_m"] < noisy["mean_rms_to_first_m"], row
        assert row["most_iterated"] == 3 and row["rollout_s_per_episode"] > 0
        rejected = sum(n for verdict, n in row["verdicts"].items() if verdict != "accepted")
        assert sum(row["failures_by"].values()) <= rejected  # blow_up and penetration name their criterion or body
    assert high["agreement_with_most_iterated"] == 1.0
    assert "| 1 | 20 | 2 |" in out.with_suffix(".md").read_text() and out.with_suffix(".png").stat().st_size > 0


def test_bad_arguments_are_named(capsys):
    with pytest.raises(SystemExit):
        newton_convergence.main(["--iterations", "5,0"])
    assert "positive integers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        newton_convergence.main(["--perturb-m", "-0.1"])
    assert "--perturb-m scales >= 0" in capsys.readouterr().err
