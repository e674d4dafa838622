"""Load-torque observer: pole placement, convergence, ramp lag 2/p."""
import numpy as np
import pytest

from identifier.observer import LoadTorqueObserver

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
