"""The teacher check's expansion-weighted figures (wc.expand.teacher.expansion_weighted) and the expansion-speed row that
carries them (benchmarks.expand_speed_report.speed_row)."""

import pytest

from benchmarks.expand_speed_report import markdown, speed_row
from wc.expand.teacher import expansion_weighted

# 8 accepted plans (Newton accepts 6) and 4 rejected plans (Newton accepts 3 of them)
CONFUSION = {"worldcontact accepted / newton accepted": 6, "worldcontact accepted / newton penetration": 2,
             "worldcontact not_lifted / newton accepted": 2, "worldcontact blow_up / newton accepted": 1,
             "worldcontact blow_up / newton blow_up": 1}


def test_a_sample_weighted_by_its_own_counts_gives_the_sample_figures():
    w = expansion_weighted(CONFUSION, accepted=8, rejected=4)
    assert w["agreement"] == pytest.approx((6 + 1) / 12)
    assert w["newton_accepts"] == pytest.approx(9 / 12)
    assert w["recall"] == pytest.approx(6 / 9)


def test_each_stratum_counts_as_many_episodes_as_it_stands_for():
    # 792 accepted episodes behave like the 8 sampled (75 % agree), 8 rejected like the 4 sampled (25 % agree)
    w = expansion_weighted(CONFUSION, accepted=792, rejected=8)
    assert w["agreement"] == pytest.approx((792 * 0.75 + 8 * 0.25) / 800)
    assert w["newton_accepts"] == pytest.approx((792 * 0.75 + 8 * 0.75) / 800)
    assert w["recall"] == pytest.approx(792 * 0.75 / (792 * 0.75 + 8 * 0.75))
    assert w["agreement"] > expansion_weighted(CONFUSION, accepted=8, rejected=4)["agreement"]


def test_an_unsampled_stratum_leaves_the_figures_undefined_and_bad_counts_are_named():
    accepted_only = {k: v for k, v in CONFUSION.items() if k.startswith("worldcontact accepted")}
    assert expansion_weighted(accepted_only, accepted=10, rejected=3)["agreement"] is None
    assert expansion_weighted(accepted_only, accepted=10, rejected=0)["agreement"] == pytest.approx(0.75)
    with pytest.raises(ValueError, match="counts must be >= 0"):
        expansion_weighted(CONFUSION, accepted=-1, rejected=4)


def test_the_speed_row_weights_a_teacher_check_by_the_expansion_and_the_table_shows_both():
    newton = [{"worlds": w, "accepted_per_min": rate, "episodes": w, "accepted": w // 2, "seconds": 30.0,
               "episodes_per_min": 2.0 * w, "acceptance": 0.5} for w, rate in ((64, 50.0), (128, 80.0))]
    expanded = {"accepted_per_min": 160.0, "acceptance_rate": 0.99, "accepted": 792, "generated": 800}
    teacher = {"plans": 12, "agreement": 7 / 12, "mean_rms_error_m": 0.03, "accepted_mean_rms_error_m": 0.02,
               "confusion": CONFUSION}
    row = speed_row(newton, expanded, teacher)
    assert (row["newton_worlds"], row["ratio"]) == (128, pytest.approx(2.0))
    assert row["teacher_agreement_expansion"] == pytest.approx((792 * 0.75 + 8 * 0.25) / 800)
    assert (row["teacher_rms_mm"], row["teacher_rms_mm_accepted"]) == (pytest.approx(30.0), pytest.approx(20.0))
    assert speed_row(newton, expanded, None)["teacher_agreement_expansion"] is None
    report = {"task": "lift_handle", "environment": {"gpu": "test GPU"}, "what": "a test", "newton": newton,
              "rows": [row | {"run": "run 9"}]}
    assert "| run 9 | 306 | 80.0 (128) | 160.0 | 2.00 | 0.99 | 0.58 (12) / 0.74 | 30.0 / 20.0 |" in markdown(report)
