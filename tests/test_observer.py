"""Load-torque observer: pole placement, convergence, ramp lag 2/p."""
import numpy as np
import pytest

from identifier.observer import LoadTorqueObserver

from .conftest import case_seed

J, T = 16.6, 1e-3


def simulate(observer, load_torque_fn, steps, torque_nm=3000.0):
    """Exact motor-shaft dynamics (fine Euler) with a known load torque; returns true and estimated T_L."""
    omega, true, est = 60.0, [], []
    observer.reset(omega, 0.0)
    for k in range(steps):
        t = k * T
        est.append(observer.update(omega, torque_nm))
        true.append(load_torque_fn(t))
        for i in range(100):
            omega += T / 100 * (torque_nm - load_torque_fn(t + i * T / 100)) / J
    return np.array(true), np.array(est)


def test_gains_place_the_double_pole():
    obs = LoadTorqueObserver(J, T, 300.0)
    a_minus_hc = np.array([[-obs.gain_speed, -1 / J], [-obs.gain_torque, 0.0]])
    np.testing.assert_allclose(np.linalg.eigvals(np.eye(2) + T * a_minus_hc), [1 - 300 * T] * 2, atol=1e-6)


def test_step_converges_and_ramp_lags_two_over_p():
    obs = LoadTorqueObserver(J, T, 250.0)
    true, est = simulate(obs, lambda t: 2000.0, 200)
    assert est[-1] == pytest.approx(2000.0, rel=1e-3)
    slope = 20_000.0   # N·m/s
    obs = LoadTorqueObserver(J, T, 250.0)
    true, est = simulate(obs, lambda t: 1000.0 + slope * t, 300)
    lag_s = (true[-1] - est[-1]) / slope
    # continuous theory: 2/p = 8 ms (Euler at T = 1 ms shifts it by less than one period)
    assert lag_s == pytest.approx(2 / 250, abs=T)


def test_rejects_unstable_pole():
    with pytest.raises(ValueError, match="p\\*T"):
        LoadTorqueObserver(J, T, 1500.0)


def test_the_gap_diagnosis_replays_the_tcus_observer_exactly():
    """hil/gap/model.ObserverReplica runs the TCU's LoadTorqueObserver over a whole record as one
    linear filter (``state_space``): the same mu^ as stepping the observer, on random speeds and
    commands (seed drawn at test time)."""

    from hil.config import load_scenario
    from hil.gap.model import ObserverReplica
    from identifier.observer import LoadTorqueObserver
    seed = case_seed()
    g = np.random.default_rng(seed)
    settings = load_scenario("scenarios/ffcc_a.toml").identifier_settings()
    n = 2000
    motor = 250.0 + np.cumsum(g.normal(0, 0.05, n))
    cmd = 2000.0 + 300.0 * g.standard_normal(n)
    v = settings.vehicle
    obs = LoadTorqueObserver(v.equivalent_inertia_kgm2, settings.period_s, settings.observer_pole_rad_s)
    te = np.concatenate([[settings.torque_demand_nm], cmd[:-1]])
    obs.reset(motor[0], te[0])
    stepped = np.array([obs.update(motor[k], te[k]) for k in range(n)]) / v.torque_per_mu_nm
    replayed = ObserverReplica(settings).mu_hat(motor, cmd)
    assert np.max(np.abs(replayed - stepped)) < 1e-9 * np.max(np.abs(stepped))
