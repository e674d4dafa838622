"""The bench's verdicts on hand-made summaries and events (every expected value written here)."""
import math

from hil.benchmarks.judge import aggregate, judge, table
from identifier.messages import IdentificationEvent

TRUE_MU, TRUE_CREEP, T_SERIOUS = 0.150, 1.20, 0.575


def event(t_s, kind, mu_ci=(math.nan, math.nan), creep_ci=(math.nan, math.nan)):
    return IdentificationEvent(int(round(t_s * 1000)), t_s, kind, 1, (0.0, 0.6, -0.6, -0.5, -1.1), 0.0, 10,
                               mu_ci, creep_ci)


def summary(identified, t_id=None, mu_err=None, creep_err=None, rt=None):
    return {"identified": identified, "t_identified_s": t_id, "peak_mu_err_percent": mu_err,
            "peak_creep_err_percent": creep_err, "rt_percent": rt}


def test_a_correct_confirmation_before_the_serious_stage_with_covering_intervals():
    ev = [event(0.52, "correction", (0.10, 0.20), (0.5, 2.0)), event(0.53, "confirmed", (0.147, 0.153), (1.1, 1.3))]
    d = judge(summary(True, 0.53, 2.9, 9.9, 40.0), ev, TRUE_MU, TRUE_CREEP, T_SERIOUS)
    assert d["correct"] and d["before_serious"] and d["correct_before_serious"] and not d["wrong_confirmation"]
    assert d["covers_peak_mu"] and d["covers_peak_creep"] and d["judged_ci_kind"] == "confirmed"
    assert math.isclose(d["ci_width_peak_mu_percent"], 4.0) and math.isclose(d["ci_width_peak_creep_percent"], 200 / 12)
    assert d["rt_percent_or_inf"] == 40.0


def test_a_confirmation_off_by_more_than_the_tolerance_is_wrong_even_if_fast():
    ev = [event(0.51, "confirmed", (0.155, 0.160), (1.0, 1.1))]
    d = judge(summary(True, 0.51, 3.1, 1.0, 13.0), ev, TRUE_MU, TRUE_CREEP, T_SERIOUS)
    assert d["wrong_confirmation"] and not d["correct"] and d["before_serious"]
    assert d["covers_peak_mu"] is False and d["covers_peak_creep"] is False


def test_unconfirmed_is_judged_on_the_last_interval_before_the_serious_stage():
    ev = [event(0.52, "correction", (0.14, 0.16), (1.0, 1.4)), event(0.56, "correction", (0.16, 0.17), (1.3, 1.4)),
          event(0.60, "unconfirmed", (0.10, 0.20), (0.0, 3.0))]
    d = judge(summary(False), ev, TRUE_MU, TRUE_CREEP, T_SERIOUS)
    assert not d["confirmed"] and not d["wrong_confirmation"] and d["rt_percent_or_inf"] == math.inf
    assert d["judged_ci_kind"] == "correction" and d["covers_peak_mu"] is False and d["covers_peak_creep"] is False
    none = judge(summary(False), [event(0.52, "correction")], TRUE_MU, TRUE_CREEP, T_SERIOUS)
    assert none["covers_peak_mu"] is None and none["ci_width_peak_mu_percent"] is None


def test_aggregate_counts_unconfirmed_as_infinite_rt():
    ok = judge(summary(True, 0.53, 1.0, 1.0, 30.0), [event(0.53, "confirmed", (0.14, 0.16), (1.0, 1.4))],
               TRUE_MU, TRUE_CREEP, T_SERIOUS)
    wrong = judge(summary(True, 0.53, 9.0, 1.0, 20.0), [event(0.53, "confirmed")], TRUE_MU, TRUE_CREEP, T_SERIOUS)
    gave_up = judge(summary(False), [], TRUE_MU, TRUE_CREEP, T_SERIOUS)
    a = aggregate([ok, wrong, gave_up, gave_up])
    assert a["draws"] == 4 and a["correct_fraction"] == 0.25 and a["wrong_confirmation_fraction"] == 0.25
    assert a["confirmed_fraction"] == 0.5 and a["coverage_peak_mu"] == 1.0 and a["coverage_draws"] == 1
    assert a["rt_median_percent"] == 30.0 and a["rt_p90_percent"] == math.inf
    text = table({"s": {**a, "oracle_rt_median_percent": 25.0}}, wide=False, markdown=False)
    assert "25%" in text and "∞" not in text.splitlines()[1].split()[1] and "25.0" in text
