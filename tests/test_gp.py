"""The form-free strategy (``gp``): its Kalman filter is the batch Gaussian posterior, it confirms
exponential curves right, and on a flat-topped curve of a form no strategy assumes it does not
confirm a wrong peak (the failure ``bayes``'s exponential form has there)."""
import dataclasses
import math

import numpy as np
import pytest

from identifier import IdentifierSettings, VehicleModel
from identifier.prior import theta_from_phi
from identifier.strategies import Sample, make_strategy

from .test_bayes import GEAR, INERTIA, PERIOD_S, RADIUS, TORQUE_PER_MU, curve, run, slip

from .conftest import case_seed


def settings(**options) -> IdentifierSettings:
    vehicle = VehicleModel(INERTIA, TORQUE_PER_MU, GEAR, RADIUS)
    return IdentifierSettings(PERIOD_S, vehicle, 0.0, (0.0, 1.0, -1.0, -0.54, -1.2), options={"gp": options})


def fresh_rng():
    seed = case_seed()
    return np.random.default_rng(seed)


def judged(event, peak_mu, peak_creep_kmh):
    mu_c, creep_c = 0.5 * sum(event.peak_mu_ci), 0.5 * sum(event.peak_creep_ci)
    return abs(mu_c / peak_mu - 1) <= 0.03 and abs(creep_c / peak_creep_kmh - 1) <= 0.10


def high_peak(rng):
    """An exponential curve of the paper's form peaking at 3.2-6 km/h (log-uniform), past the first bound."""
    return np.array([rng.uniform(0.08, 0.2), math.exp(rng.uniform(math.log(3.2), math.log(6.0))), 0.0,
                     rng.uniform(0.6, 1.0), 2.0])


def test_the_filter_equals_the_batch_gaussian_posterior():
    """The curve values' posterior after a few samples, by the strategy's Kalman filter, against the
    same linear-Gaussian model conditioned in one go here: x = (omega_0, w_1..w_K, m), independent
    priors, y_k = omega_0 + sum_j (a T_j - b_j^T m + w_j) + n_k, w_j ~ N(0, q_j) with the q_j the filter
    took (they follow the posterior mean's slope: test_the_process_noise_follows_the_slope)."""
    rng = fresh_rng()
    strat = make_strategy("gp", settings(grid_points=12, creep_min_kmh=0.1, creep_max_kmh=3.0, length_log=0.3,
                                        prior_mu=0.15, prior_mu_std=0.1))
    for k in range(50):      # the baseline: noise and train speed before the slip
        strat.on_reading(k, 250.0 + 0.005 * rng.standard_normal(), 10.0)
    samples = []
    omega = 250.0
    for k in range(50, 58):
        y = omega + 0.005 * rng.standard_normal()
        samples.append(Sample(k, k * PERIOD_S, 0.0, math.nan, math.nan, y, 10.0, 2000.0 + 100 * rng.random()))
        omega += 0.04 + 0.01 * rng.random()
    qs = []
    for s in samples:
        strat.add_sample(s)
        qs.append(strat.q_last if len(qs) else None)      # the process noise of each step (the slope's)
    # the batch posterior, built from the model's definition (module docstring of identifier/strategies/gp.py)
    g = strat.log_x.size
    K = len(samples) - 1
    sigma2 = strat.sigma_y ** 2
    a = PERIOD_S / INERTIA
    d = strat.log_x[:, None] - strat.log_x[None, :]
    prior_cov = 0.1 ** 2 * np.exp(-0.5 * (d / 0.3) ** 2)
    n = 1 + K + g
    mean = np.concatenate([[samples[0].motor_speed_rad_s], np.zeros(K), np.full(g, 0.15)])
    cov = np.zeros((n, n))
    cov[0, 0] = sigma2
    cov[1:1 + K, 1:1 + K] = np.diag(qs[1:])
    cov[1 + K:, 1 + K:] = prior_cov
    rows, offsets = [], []
    row, offset = np.zeros(n), 0.0
    row[0] = 1.0
    for j in range(1, K + 1):
        h = lambda s: strat.h(strat.creep_for_likelihood(s))  # noqa: E731
        b = a * TORQUE_PER_MU * 0.5 * (h(samples[j - 1]) + h(samples[j]))
        row = row.copy()
        row[j] += 1.0
        row[1 + K:] -= b
        offset += a * samples[j - 1].torque_nm
        rows.append(row)
        offsets.append(offset)
    H = np.array(rows)
    y = np.array([s.motor_speed_rad_s for s in samples[1:]])
    S = H @ cov @ H.T + sigma2 * np.eye(K)
    gain = cov @ H.T @ np.linalg.inv(S)
    post_mean = mean + gain @ (y - (H @ mean + np.array(offsets)))
    post_cov = cov - gain @ H @ cov
    np.testing.assert_allclose(strat.z[1:], post_mean[1 + K:], rtol=0, atol=1e-9)
    np.testing.assert_allclose(strat.P[1:, 1:], post_cov[1 + K:, 1 + K:], rtol=0, atol=1e-9)


def test_exponential_curves_confirmed_right():
    """Curves of the paper's form with a clear peak: confirmed, within the tolerance, or unconfirmed;
    never wrong, and most confirmed."""
    rng = fresh_rng()
    confirmed = 0
    for i in range(5):
        phi = np.array([rng.uniform(0.08, 0.2), rng.uniform(0.8, 1.6), 0.0, rng.uniform(0.6, 1.0), 2.0])
        pre, samples = slip(curve(theta_from_phi(phi)), phi[0] * 1.06, rng, creep0_kmh=0.3 * phi[1])
        strat = make_strategy("gp", settings(), seed=i)
        e = run(strat, pre, samples)[-1]
        print(phi[:2], e.kind, e.peak_mu_ci, e.peak_creep_ci)
        if e.kind == "confirmed":
            confirmed += 1
            assert judged(e, phi[0], phi[1]), (phi, e)
    assert confirmed >= 3


def test_a_flat_top_of_another_form_is_not_confirmed_wrongly():
    """mu(v) = peak_mu (x e^(1 - x))^p, x = v / v_p, p 0.25-0.4: a flat, skewed top (neither the
    exponential form nor Polach's).  Confirmed only within the tolerance; the last 90 % peak-creep
    interval holds the truth in most trials."""
    rng = fresh_rng()
    covered = 0
    for i in range(4):
        mp, vp, p = rng.uniform(0.08, 0.2), rng.uniform(0.9, 2.0), rng.uniform(0.25, 0.4)
        mu_of = lambda v, mp=mp, vp=vp, p=p: mp * (max(v, 0.0) / vp * math.exp(1 - max(v, 0.0) / vp)) ** p  # noqa: E731
        pre, samples = slip(mu_of, mp * 1.06, rng, creep0_kmh=0.3 * vp)
        strat = make_strategy("gp", settings(), seed=i)
        e = run(strat, pre, samples)[-1]
        print(f"peak {mp:.3f} at {vp:.2f} km/h, p {p:.2f} ->", e.kind, e.peak_mu_ci, e.peak_creep_ci)
        if e.kind == "confirmed":
            assert judged(e, mp, vp), (mp, vp, p, e)
        covered += e.peak_creep_ci[0] <= vp <= e.peak_creep_ci[1]
    assert covered >= 3


@pytest.mark.parametrize("peak", ["below the first bound", "past it"])
def test_compiled_and_numpy_paths_agree(peak):
    """identifier/kernels.py's gp_update and gp_peak against the strategy's numpy reference on the
    same slip: the same posterior, the same events and intervals, open or closed alike, and (a peak
    past 3 km/h) the same grown range."""
    rng = fresh_rng()
    if peak == "past it":
        phi = high_peak(rng)
        pre, samples = slip(curve(theta_from_phi(phi)), phi[0] * 1.06, rng, creep0_kmh=0.3 * phi[1],
                            max_creep_kmh=2.5 * phi[1])
    else:
        phi = np.array([rng.uniform(0.08, 0.2), rng.uniform(0.8, 1.6), 0.0, rng.uniform(0.6, 1.0), 2.0])
        pre, samples = slip(curve(theta_from_phi(phi)), phi[0] * 1.06, rng, creep0_kmh=0.3 * phi[1])
    runs = []
    for compiled in (True, False):
        strat = make_strategy("gp", settings(compiled=compiled), seed=7)
        assert strat._compiled == compiled
        runs.append((strat, run(strat, pre, samples)))
    (a, ev_a), (b, ev_b) = runs
    assert [e.kind for e in ev_a] == [e.kind for e in ev_b] and ev_a[-1].step == ev_b[-1].step
    assert [e.peak_open for e in ev_a] == [e.peak_open for e in ev_b] and a.bound_kmh == b.bound_kmh
    assert (a.bound_kmh > 3.0) == (peak == "past it")
    np.testing.assert_allclose(a.z, b.z, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-8, atol=1e-14)
    # rounding (the Cholesky factor's, the sums' order) moves a parabola's vertex by ~1e-8 relative;
    # a draw whose maximum moved to another grid point would move it by ~1e-1
    for ea, eb in zip(ev_a, ev_b):
        np.testing.assert_allclose(ea.peak_mu_ci + ea.peak_creep_ci, eb.peak_mu_ci + eb.peak_creep_ci, rtol=1e-6)
        np.testing.assert_allclose(ea.params, eb.params, rtol=1e-6)


def test_intervals_cover_the_truth_about_as_often_as_they_say():
    """40 exponential curves of the bench's families' peak box: the last 90 % intervals hold the true
    peak mu and peak creep in at least 26 (36 expected if calibrated): a guard against a gross
    miscalibration, the bench measures it."""
    from identifier.prior import CurvePrior
    from .test_bayes import draw_curve
    rng = fresh_rng()
    prior = CurvePrior.from_options({"peak_mu": [0.05, 0.25], "peak_creep_kmh": [0.4, 3.0], "shape_a": [0.3, 2.5],
                                     "shape_r": [1.3, 4.0]})
    trials, covered_mu, covered_creep = 40, 0, 0
    for i in range(trials):
        phi, theta = draw_curve(rng, prior)
        pre, samples = slip(curve(theta), phi[0] * 1.06, rng, creep0_kmh=0.3 * phi[1])
        e = run(make_strategy("gp", settings(), seed=i), pre, samples)[-1]
        covered_mu += e.peak_mu_ci[0] <= phi[0] <= e.peak_mu_ci[1]
        covered_creep += e.peak_creep_ci[0] <= phi[1] <= e.peak_creep_ci[1]
    print("90 % intervals covered peak mu", covered_mu, "peak creep", covered_creep, "of", trials)
    # This loop's own computation over 1 500 draws (seeds 1000000-1000399, 3000000-3001099) covered peak mu
    # 1 464 times (0.976) and peak creep 1 356 (0.904, 95 % lower bound 0.888).  Covered ~ Binomial(40, p):
    # at p = 0.888, P(< 26) = 1.4e-5 (P(< 30), the former floor, is 3.6e-3: one run in 300 failed by chance);
    # peak mu's P(< 26) at 0.967 is 1e-12.
    assert covered_mu >= 26 and covered_creep >= 26


def test_the_process_noise_follows_the_slope():
    """q = (dt c / J)^2 (model_mu_std^2 + slope^2 creep_var / 2): with the posterior mean set to a line
    of known slope in v_s, slope_per_kmh returns it, and the step's q carries it."""
    rng = fresh_rng()
    model_mu_std = rng.uniform(1e-4, 1e-3)
    strat = make_strategy("gp", settings(model_mu_std=model_mu_std))
    for k in range(50):
        strat.on_reading(k, 250.0 + 0.005 * rng.standard_normal(), 10.0)
    y0 = 250.0
    strat.add_sample(Sample(50, 0.05, 0.0, math.nan, math.nan, y0, 10.0, 2000.0))
    slope = rng.uniform(0.02, 0.3)
    strat.z[1:] = 0.05 + slope * np.exp(strat.log_x)
    v = rng.uniform(0.3, 2.0)
    assert abs(strat.slope_per_kmh(v) - slope) < 1e-9
    y1 = (v / 3.6 + 10.0) * GEAR / RADIUS        # a reading at creep v
    strat.add_sample(Sample(51, 0.051, v, math.nan, math.nan, y1, 10.0, 2000.0))
    sigma_y = strat.sigma_y
    creep_noise = 3.6 * RADIUS / GEAR * sigma_y
    expected = (PERIOD_S * TORQUE_PER_MU / INERTIA) ** 2 * (model_mu_std ** 2 + slope ** 2 * creep_noise ** 2 / 2)
    assert abs(strat.q_last / expected - 1) < 1e-6


def test_peaks_past_the_first_bound_are_followed_and_confirmed_right():
    """Curves peaking at 3.2-6 km/h, past ``upper_peak_creep_kmh`` (3): the working range grows with the
    rise; every confirmation is right (within the tolerance), closed and inside the grown range, and most
    are confirmed with a peak-creep interval that holds the truth.  (400 such curves, seeds 1000-1099 x 4,
    offline: 400 confirmed right, 391 closed intervals holding the true peak creep; the 9 misses lie below the
    interval's low end by under 0.1 %.)  12 curves, at least 10 confirmed and 8 covering: with a miss rate of
    4 % (above the 2.25 % measured) the chance of 5 or more misses in 12 is 6e-5.  (4 curves and 3 covering
    failed on HIL_TEST_SEED=397632802: two misses by 0.03 % and 0.006 %.)"""
    rng = fresh_rng()
    confirmed = covered = 0
    for i in range(12):
        phi = high_peak(rng)
        pre, samples = slip(curve(theta_from_phi(phi)), phi[0] * 1.06, rng, creep0_kmh=0.3 * phi[1],
                            max_creep_kmh=2.5 * phi[1])
        strat = make_strategy("gp", settings(), seed=i)
        e = run(strat, pre, samples)[-1]
        print(phi[:2], e.kind, e.peak_mu_ci, e.peak_creep_ci, "open" if e.peak_open else "closed",
              f"range {strat.bound_kmh:.3f} km/h")
        assert strat.bound_kmh > 3.0 and strat.bound_kmh <= 10.0
        if e.kind == "confirmed":
            confirmed += 1
            assert judged(e, phi[0], phi[1]) and not e.peak_open and e.peak_creep_ci[1] < strat.bound_kmh, (phi, e)
        covered += not e.peak_open and e.peak_creep_ci[0] <= phi[1] <= e.peak_creep_ci[1]
    assert confirmed >= 10 and covered >= 8


def test_in_open_loop_a_slip_that_starts_past_the_peak_confirms_no_point_at_its_edge():
    """A rail that changes under an open-loop slip can make mu^ fall from the slip's first sample (a curve whose
    peak lies below the creep the slip starts from, as a transition to a patch leaves it): every sample then
    lies past the peak and the posterior's maximum is the lowest creep seen.  With the guard at the data's edge
    (``open_loop_edge``, the default) nothing is confirmed; without it (the same draws) the lowest creep seen is
    confirmed as a point, an interval of zero width that misses the true peak.  (Offline, 300 such slips: without
    the guard 296 confirmed so; with it none confirmed.)"""
    rng = fresh_rng()
    unguarded = []
    for i in range(12):
        phi = np.array([rng.uniform(0.08, 0.2), rng.uniform(0.5, 1.5), 0.0, rng.uniform(0.6, 1.0), 2.0])
        pre, samples = slip(curve(theta_from_phi(phi)), phi[0] * 1.06, rng, creep0_kmh=rng.uniform(1.2, 2.0) * phi[1])
        guarded = [e for e in run(make_strategy("gp", settings(), seed=1), pre, samples) if e.kind == "confirmed"]
        assert not guarded, (phi, guarded[0])
        off = [e for e in run(make_strategy("gp", settings(open_loop_edge=False), seed=1), pre, samples)
               if e.kind == "confirmed"]
        print(phi[:2], "without the guard:", off[0].peak_creep_ci if off else "nothing confirmed")
        unguarded += [(phi, e) for e in off[:1]]
    # the ablation: without the guard the same slips are confirmed as points that miss the peak (296 of 300
    # offline; at 90 % a slip, fewer than 6 of 12 with a chance of 5e-5)
    wrong_points = [e for phi, e in unguarded
                    if e.peak_creep_ci[0] == e.peak_creep_ci[1] and not e.peak_creep_ci[0] <= phi[1] <= e.peak_creep_ci[1]]
    assert len(wrong_points) >= 6, unguarded


def test_a_range_that_cannot_see_the_peak_reports_its_intervals_open_and_never_covering():
    """The same kind of curve with the range held at its first bound (``peak_creep_cap_kmh`` = 3): the
    TCU gives up when the creep passes 3 km/h with the rise still going on; its intervals are open (the
    upper ends are the bound, 3 km/h, and the rise's mu) and the bench's judge counts neither as
    covering, though the truth's peak mu may lie inside the published numbers."""
    from hil.benchmarks.judge import judge

    rng = fresh_rng()
    phi = high_peak(rng)
    pre, samples = slip(curve(theta_from_phi(phi)), phi[0] * 1.06, rng, creep0_kmh=0.3 * phi[1],
                        max_creep_kmh=2.5 * phi[1])
    events = run(make_strategy("gp", settings(peak_creep_cap_kmh=3.0)), pre, samples)
    e = events[-1]
    print(phi[:2], e.kind, e.peak_mu_ci, e.peak_creep_ci, e.peak_open)
    assert e.kind == "unconfirmed" and e.peak_open and e.peak_creep_ci[1] == 3.0
    verdict = judge({"identified": False, "rt_percent": None}, events, phi[0], phi[1], None)
    assert verdict["judged_ci_open"] is True
    assert verdict["covers_peak_mu"] is False and verdict["covers_peak_creep"] is False
    # the same numbers closed would be judged on their values
    closed = [dataclasses.replace(x, peak_open=False, peak_mu_ci=(0.0, 1.0), peak_creep_ci=(0.0, 10.0)) for x in events]
    assert judge({"identified": False, "rt_percent": None}, closed, phi[0], phi[1], None)["covers_peak_creep"] is True


def test_below_the_first_bound_the_grown_grid_changes_nothing():
    """A curve peaking below 3 km/h: every event with the default range (its grid continued past
    ``creep_max_kmh`` to the cap, 10 km/h) equals, to the last bit, the one with the range held at 3 km/h
    (``peak_creep_cap_kmh`` = 3: the 64 creeps of before), and the first 64 creeps are those creeps."""
    rng = fresh_rng()
    phi = np.array([rng.uniform(0.08, 0.2), rng.uniform(0.8, 2.4), 0.0, rng.uniform(0.6, 1.0), 2.0])
    pre, samples = slip(curve(theta_from_phi(phi)), phi[0] * 1.06, rng, creep0_kmh=0.3 * phi[1])
    grown, held = make_strategy("gp", settings(), seed=3), make_strategy("gp", settings(peak_creep_cap_kmh=3.0), seed=3)
    assert held.log_x.size == 64 and grown.log_x.size > 64 and math.exp(grown.log_x[-1]) >= 10.0
    assert np.array_equal(grown.log_x[:64], np.linspace(math.log(0.02), math.log(4.0), 64))
    key = lambda e: (e.step, e.kind, e.correction, e.params, e.samples, e.peak_mu_ci, e.peak_creep_ci, e.peak_open)  # noqa: E731
    a, b = [key(e) for e in run(grown, pre, samples)], [key(e) for e in run(held, pre, samples)]
    print(phi[:2], len(a), "events, last", a[-1][1], a[-1][6])
    assert a == b and len(a) > 3
    assert np.array_equal(grown.z[:65], held.z) and np.array_equal(grown.P[:65, :65], held.P)


@pytest.mark.parametrize("key, value", [("grid_points", 3), ("length_log", 0.0), ("draws", 2.5),
                                        ("confirm_level", 1.0), ("creep_max_kmh", 0.01),
                                        ("upper_peak_creep_kmh", 9.0), ("peak_creep_cap_kmh", 2.0),
                                        ("range_growth", 1.0), ("model_mu_std", math.nan), ("bogus", 1),
                                        ("rail_changes", 1), ("change_window", 1), ("change_settle_s", -0.1),
                                        ("change_fall_slope", math.inf), ("one_rail", 1), ("stationary_blocks", 3),
                                        ("stationary_sigmas", -1.0), ("estimate_agrees", "yes")])
def test_bad_options_are_refused_by_name(key, value):
    with pytest.raises(ValueError, match=key):
        make_strategy("gp", settings(**{key: value}))


def test_a_rail_peaking_just_below_3_kmh_is_confirmed_and_a_held_range_says_open_on_the_bus(tmp_path):
    """The issue's case, real runs (plant and TCU over the in-process bus): FFCC-a's vehicle with a fault
    curve peaking at 2.7-2.95 km/h, just below the first bound.  By default ``hil run`` confirms it with
    a closed 90 % peak-creep interval holding the true peak (before, the interval sat at 3.000 .. 3.000
    and the run ended unconfirmed).  With the range held at 3 km/h the TCU gives up, and the open flag
    travels in TcuInterval to ``--json``, into the log's /tcu/identification, and through a replay."""
    import json
    import re

    from hil.log.read import read_log

    from .conftest import SCENARIOS, hil

    rng = fresh_rng()
    peak_creep = rng.uniform(2.7, 2.95)
    l0, l1, l2, t1, t2 = (float(x) for x in theta_from_phi(np.array([0.15, peak_creep, 0.0, 1.0, 2.0])))
    text = re.sub(r"\[curves\.fault\].*?\n\n", f"[curves.fault]\nlambda0 = {l0!r}\nlambdas = [{l1!r}, {l2!r}]\n"
                  f"taus = [{t1!r}, {t2!r}]\n\n", (SCENARIOS / "ffcc_a.toml").read_text(), flags=re.S)
    scenario = tmp_path / "near3.toml"
    scenario.write_text(text.replace('name = "ffcc_a"', 'name = "near3"'))
    runs = {}
    for name, extra in (("default", []), ("held", ["--set", "identifier.options.gp.peak_creep_cap_kmh=3.0"])):
        r = hil("run", scenario, "--bus", "inprocess", "--no-rrd", "--json", "--out", tmp_path / name, *extra)
        assert r.returncode == 0, r.stderr
        runs[name] = json.loads(r.stdout)
        s = runs[name]
        print(f"peak {peak_creep:.3f} km/h, {name}: identified {s['identified']}, peak creep {s['peak_creep_ci']}, "
              f"open {s['peak_interval_open']}")
    s = runs["default"]
    assert s["identified"] and s["peak_interval_open"] is False
    assert s["peak_creep_ci"][0] <= peak_creep <= s["peak_creep_ci"][1] < 3.75
    s = runs["held"]
    assert s["unconfirmed"] and s["peak_interval_open"] is True and s["peak_creep_ci"][1] == 3.0
    logged = [m for _, _, m in read_log(s["mcap"], topics={"/tcu/identification"}).messages]
    assert logged[-1].kind == "unconfirmed" and logged[-1].peak_open is True
    flags = [m.peak_open for m in logged]
    print("open flags logged:", "".join("o" if f else "c" for f in flags))
    assert flags[0]        # at the slip's start the rise goes on: the peak lies past the creeps seen
    assert all(m.peak_creep_ci[1] == 3.0 for m in logged if m.peak_open)      # an open interval ends at the bound
    rp = hil("replay", s["mcap"], "--json")
    assert rp.returncode == 0, rp.stderr
    rs = json.loads(rp.stdout)
    assert rs["matches_log"] is True and rs["peak_interval_open"] is True and rs["peak_creep_ci"] == s["peak_creep_ci"]


def held_creep_rail_change(rng, dry_phi, wet_phi, change_s=0.1, hold_s=0.25, sweep_to_kmh=2.0, sweep_s=0.35):
    """(readings before, samples) of a closed loop on a rail that changes under it: the creep held at
    0.5 km/h on the dry curve, then (from t = 0) the rail blends linearly to the wet curve over
    ``change_s`` while the creep is held near 0.6 km/h (a loop catching the slip, with a 8 Hz dither of
    0.05 km/h), then swept to ``sweep_to_kmh`` over ``sweep_s``.  The torque is what makes the wheelset
    (J dw/dt = T - c mu) follow that creep; the observer's mu^ is the true mu with noise."""
    dry, wet = curve(theta_from_phi(dry_phi)), curve(theta_from_phi(wet_phi))
    to_kmh, train_ms = 3.6 * RADIUS / GEAR, 10.0
    omega_of = lambda v: (v / 3.6 + train_ms) / (RADIUS / GEAR)  # noqa: E731
    pre = [(k, omega_of(0.5) + 0.005 * rng.standard_normal(), train_ms + 0.002 * rng.standard_normal())
           for k in range(200)]

    def creep(t):
        v = 0.5 + 0.1 * min(max(t, 0.0) / 0.03, 1.0) + 0.05 * math.sin(2 * math.pi * 8.0 * t)
        return v + (sweep_to_kmh - 0.6) * min(max(t - hold_s, 0.0) / sweep_s, 1.0)

    samples = []
    for k in range(200, 200 + round((hold_s + sweep_s) / PERIOD_S)):
        t = (k - 200) * PERIOD_S
        w = min(max(t / change_s, 0.0), 1.0)
        v, v_next = creep(t), creep(t + PERIOD_S)
        mu = (1 - w) * dry(v) + w * wet(v)
        torque = TORQUE_PER_MU * mu + INERTIA * (omega_of(v_next) - omega_of(v)) / PERIOD_S
        y, v_t = omega_of(v) + 0.005 * rng.standard_normal(), train_ms + 0.002 * rng.standard_normal()
        samples.append(Sample(k, k * PERIOD_S, to_kmh * y - 3.6 * v_t, mu + 0.001 * rng.standard_normal(),
                              math.nan, y, v_t, torque))
    return pre, samples


def test_in_closed_loop_a_change_of_rail_is_dated_and_no_wrong_peak_is_confirmed():
    """A rail that changes under a held creep (``held_creep_rail_change``): as an open-loop identifier
    the strategy reads the fall of mu the change makes as the fall past a peak and confirms a peak
    creep far below the wet rail's; told it is in closed loop (``Strategy.closed_loop``, as the TCU
    does), it drops the samples of the change and confirms only once the creep has swept the wet
    rail's peak, within 10 % of it."""
    rng = fresh_rng()
    wet = np.array([rng.uniform(0.08, 0.15), rng.uniform(1.0, 1.4), 0.0, rng.uniform(0.6, 1.0), 2.0])
    dry = np.array([0.3, 1.5, 0.0, 0.8, 2.0])
    pre, samples = held_creep_rail_change(rng, dry, wet)
    open_loop = run(make_strategy("gp", settings(), seed=3), pre, samples)
    closed = make_strategy("gp", settings(), seed=3)
    closed.closed_loop = True
    events = run(closed, pre, samples)
    first, last = open_loop[-1], events[-1]
    print(wet[:2], "open loop:", first.kind, first.t_s, first.peak_creep_ci, "closed loop:", last.kind, last.t_s,
          last.peak_creep_ci, closed.restarts, "restarts")
    assert first.kind == "confirmed" and first.peak_creep_ci[1] < 0.8 * wet[1]
    assert closed.restarts >= 1
    assert [e.kind for e in events].count("confirmed") == 1 and last.kind == "confirmed"
    assert abs(0.5 * sum(last.peak_creep_ci) / wet[1] - 1) <= 0.10
    # what it states it rests on: the samples since its last restart, all on the wet rail (the blend ends 0.1 s after
    # the first sample), to the confirmation's own; in open loop every event's samples run from the slip's first
    assert last.samples_to_s == last.t_s and last.samples_from_s >= samples[0].t_s + 0.1
    assert all(e.samples_from_s == samples[0].t_s and e.samples_to_s == e.t_s for e in open_loop)
    # the closed loop's options off (the dating, the interval floors), it identifies as the open one did without
    # its guard at the data's edge
    off = make_strategy("gp", settings(rail_changes=False, floor_peak_mu=0.0, floor_peak_creep_kmh=0.0), seed=3)
    off.closed_loop = True
    unguarded = run(make_strategy("gp", settings(open_loop_edge=False), seed=3), pre, samples)
    assert [(e.step, e.peak_creep_ci) for e in run(off, pre, samples)] == [(e.step, e.peak_creep_ci) for e in unguarded]
