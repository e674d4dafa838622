"""Observer-aware strategies on an independent simulation of wheelset + sensors + load-torque observer.

The simulation below shares no code with identifier/strategies/observer_aware.py: the wheel speed is
integrated with 20 RK4 sub-steps per period, the observer is written from method.md §4's matrices
(x^(k+1) = (I + A T) x^(k) + B T T_e + H T (y(k) - C x^(k))), and the samples carry what the TCU
gives an observer-aware strategy (creep of the same instant, mu^ = T^_L / c, innovation y - omega^).
"""
import math

import numpy as np
import pytest

from identifier import IdentifierSettings, VehicleModel, make_strategy
from identifier.curve import mu_model
from identifier.strategies import Sample
from identifier.strategies.observer_aware import ObserverAwareModel

from .test_strategies import FFCC_A, assert_confirmed_near_the_peak, feed

NFCC_0 = np.array([0.0, 1.0, -1.0, -0.54, -1.2])
J, C, GEAR, RADIUS, T, POLE, TORQUE = 16.6, 21373.0, 2.788, 0.4375, 1e-3, 400.0, 3400.0
TRAIN_MS = 10.0


def settings(**kw) -> IdentifierSettings:
    vehicle = VehicleModel(equivalent_inertia_kgm2=J, torque_per_mu_nm=C, gear_ratio=GEAR, wheel_radius_m=RADIUS)
    return IdentifierSettings(period_s=T, vehicle=vehicle, torque_demand_nm=TORQUE, initial_guess=tuple(NFCC_0),
                              observer_pole_rad_s=POLE, **kw)


def creep_kmh(omega):
    return 3.6 * (omega / GEAR * RADIUS - TRAIN_MS)


def simulate(theta=FFCC_A, steps=150, seed=0, speed_noise=0.005, train_noise=0.002):
    """Samples from the first period after the fault; the plant sat on NFCC-0 at equilibrium before it."""
    rng = np.random.default_rng(seed)
    v0 = 0.05
    while mu_model(np.array([v0]), NFCC_0)[0] < TORQUE / C:      # equilibrium creep on the normal curve
        v0 += 1e-4
    omega = (v0 / 3.6 + TRAIN_MS) * GEAR / RADIUS

    def d_omega(w):
        return (TORQUE - C * mu_model(np.array([creep_kmh(w)]), theta)[0]) / J

    A = np.array([[0.0, -1.0 / J], [0.0, 0.0]])
    B = np.array([1.0 / J, 0.0])
    H = np.array([2 * POLE, -J * POLE ** 2])
    xhat = np.array([omega, TORQUE])                               # settled before the fault
    samples, true_mu = [], []
    for k in range(steps):
        h = T / 20
        for _ in range(20):                                        # the fault is active from t = 0
            k1 = d_omega(omega)
            k2 = d_omega(omega + h / 2 * k1)
            k3 = d_omega(omega + h / 2 * k2)
            k4 = d_omega(omega + h * k3)
            omega += h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        y = omega + rng.normal(0.0, speed_noise)
        v_meas = (y / GEAR * RADIUS - (TRAIN_MS + rng.normal(0.0, train_noise))) * 3.6
        innovation = y - xhat[0]
        samples.append(Sample(k + 1, (k + 1) * T, float(v_meas), float(xhat[1] / C), float(innovation)))
        true_mu.append(mu_model(np.array([creep_kmh(omega)]), theta)[0])
        xhat = xhat + A @ xhat * T + B * T * TORQUE + H * T * innovation
    return samples, np.array(true_mu)


def test_model_predicts_the_simulated_observer_output_with_the_true_curve():
    samples, true_mu = simulate(seed=1, speed_noise=0.0, train_noise=0.0)
    v = np.array([s.creep_speed_kmh for s in samples])
    mu_hat = np.array([s.mu_hat for s in samples])
    model = ObserverAwareModel(settings())
    pred = model.predict_curve(v, FFCC_A, mu_hat[0], samples[0].speed_innovation_rad_s)
    # the observer lags the true mu by ~1e-2 right after the fault; the model follows it to ~1e-4
    assert np.max(np.abs(mu_hat[:10] - true_mu[:10])) > 5e-3
    assert np.max(np.abs(mu_hat - pred)) < 3e-4
    # the same recursion step by step (the particle filter's path) gives the same prediction
    m = mu_model(v, FFCC_A)
    np.testing.assert_allclose(model.run(m, mu_hat[0], samples[0].speed_innovation_rad_s), pred, atol=1e-12)


@pytest.mark.parametrize("name", ["nlls_oa", "proposed_oa"])
def test_recovers_a_known_curve_from_the_observer_transient(name):
    samples, _ = simulate(seed=2)
    strat = make_strategy(name, settings(), seed=3)
    assert_confirmed_near_the_peak(strat, feed(strat, samples))
    assert strat.observer_model_metrics(strat.theta)["r2_observer_model"] > 0.99


@pytest.mark.parametrize("name", ["nlls_oa", "proposed_oa"])
def test_same_seed_same_result(name):
    samples, _ = simulate(seed=4, steps=40)
    runs = []
    for seed in (5, 5, 6):
        strat = make_strategy(name, settings(), seed=seed)
        feed(strat, samples)
        runs.append(strat.theta.copy())
    np.testing.assert_array_equal(runs[0], runs[1])
    if name == "proposed_oa":
        assert not np.array_equal(runs[0], runs[2])


@pytest.mark.parametrize("name", ["nlls_oa", "proposed_oa"])
def test_bad_samples_never_give_nan_parameters(name):
    samples, _ = simulate(seed=5, steps=60)
    s = settings(options={name: {"noise_std": 1e-9, "particles": 200}} if name == "proposed_oa" else {})
    strat = make_strategy(name, s, seed=0)
    bad = [Sample(10_000 + k, 1.0, v, m, e) for k, (v, m, e) in enumerate(
        [(math.nan, 0.1, 0.0), (0.5, math.inf, 0.0), (-math.inf, 0.1, 0.0), (0.8, 1e6, 0.0), (1e6, 0.1, math.nan),
         (0.7, -1e6, 1e9)])]
    for k, smp in enumerate(samples):
        strat.add_sample(smp)
        if k % 7 == 0:
            for b in bad:
                strat.add_sample(b)
        assert np.all(np.isfinite(strat.theta)), f"NaN parameters after sample {k}"
        if name == "proposed_oa" and strat.prelim_done:
            assert np.all(np.isfinite(strat.particles)) and np.all(np.isfinite(strat.weights))


def test_first_sample_without_innovation_is_handled():
    samples, _ = simulate(seed=6, steps=30)
    first = samples[0]
    samples[0] = Sample(first.step, first.t_s, first.creep_speed_kmh, first.mu_hat)     # innovation NaN
    strat = make_strategy("proposed_oa", settings(), seed=0)
    feed(strat, samples)
    assert strat.prelim_done and np.all(np.isfinite(strat.theta))


def test_tcu_feeds_observer_aware_strategies_from_the_slip_start(ffcc_a_path):
    """Through the real TCU and plant: samples from the detected slip start, creep of the same instant."""
    from hil.benchmarks.identify import generate
    from hil.config import load_scenario
    from identifier import TractionIdentifier

    sc = load_scenario(ffcc_a_path)
    data = generate(sc, 1)
    paper = TractionIdentifier(sc.identifier_settings(), "proposed", 1)
    oa = TractionIdentifier(sc.identifier_settings(), "proposed_oa", 1)
    first = {}
    for r in data.readings[:700]:
        for name, ident in (("paper", paper), ("oa", oa)):
            out = ident.on_sensor(r)
            if ident.strategy.samples and name not in first:
                first[name] = r.step
    assert oa.detector.detected_step == paper.detector.detected_step
    assert first["oa"] == oa.detector.detected_step + oa.detector.consecutive - 1   # fed at detection time
    v, _ = oa.strategy.data()
    assert len(v) >= 2 and oa.strategy._eta0 == oa.strategy._eta0                   # finite innovation
    settle = round(sc.identifier_settings().settle_time_s / sc.run.exchange_period_s)
    assert first["paper"] - paper.detector.detected_step == settle                   # the paper's path unchanged
    assert out is not None
