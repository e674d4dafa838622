"""The information limit of ``hil bench identify`` (hil/benchmarks/oracle.py) on real plant runs of
drawn fault curves: it knows the family's prior, so its intervals must cover the truth as they say,
and it may not be later than the strategy that uses a broader prior on the same samples."""


from hil.benchmarks.identify import generate, replay, run_oracle
from hil.config import parse_scenario
from plant import families

from .conftest import SCENARIOS, case_seed

DRAWS = 12


def test_the_oracle_covers_the_truth_and_is_not_later_than_bayes():
    seed = case_seed()
    base = (SCENARIOS / "ffcc_a.toml").read_text()
    covered, runs, not_later = 0, 0, 0
    for i in range(DRAWS):
        sc = parse_scenario(families.draw_scenario_text(base, "exp", seed, i), f"draw {i}")
        data = generate(sc, i + 1)
        o = run_oracle(data, "exp", [seed, i], 2000)
        if o["oracle_t_confirmed_s"] is None:
            continue
        runs += 1
        v_true, mu_true = sc.fault_curve.peak()
        (m0, m1), (c0, c1) = o["oracle_peak_mu_ci"], o["oracle_peak_creep_ci"]
        covered += (m0 <= mu_true <= m1) and (c0 <= v_true <= c1)
        summary, _ = replay(data, "bayes", None)
        t_bayes = summary.get("t_identified_s")
        not_later += t_bayes is None or o["oracle_t_confirmed_s"] <= t_bayes + 1e-9
        assert o["oracle_ess"] >= 30
    print("oracle confirmed", runs, f"of {DRAWS}; both 90 % intervals covered", covered, "; not later than bayes",
          not_later)
    assert runs >= DRAWS - 4
    # both intervals cover together with probability >= 0.80 for a calibrated oracle (two 90 % intervals:
    # 1 - 0.1 - 0.1; 0.81 if independent, nearer 0.88 as they are correlated).  Misses ~ Binomial(runs <= 12,
    # q <= 0.2): P(9 or more of 12) = sum_{k>=9} C(12,k) 0.2^k 0.8^(12-k) = 6.2e-5, under once in 10 000 runs
    # (8 or more: 5.8e-4, once in 1 700, hence 8 allowed); an oracle that keeps to its prior misses most
    # curves drawn away from it
    assert covered >= runs - 8
    assert not_later >= runs - 1        # a broader prior cannot know more, up to the oracle's own sampling
