"""The likelihood of the motor-speed readings under a candidate friction curve: one scalar Kalman
filter per candidate, the numpy reference (``identifier/kernels.py`` has its compiled twin for the
``bayes`` strategy; the offline oracle of ``hil bench identify`` runs this one on many candidates).

The wheelset between two readings, the torque held (paper eq. A, J = J_eq, c = torque per unit mu):

    omega(k+1) = omega(k) + (dt / J) (T_e(k) - c mbar(k)) + w(k),   w ~ N(0, q dt / T)
    mbar(k)    = (M(v_s(k)) + M(v_s(k+1))) / 2                       (trapezoid: mu changes within the period)
    y(k)       = omega(k) + n(k),                                     n ~ N(0, sigma_y^2)

Kalman filter per candidate j (P, S and K are the same for every candidate, so they are scalars):

    omega^-_j = omega^_j + (dt / J) (T_e - c mbar_j)     P- = P + q dt / T       (predict)
    e_j = y - omega^-_j                                   S = P- + sigma_y^2      (innovation)
    log L_j += -e_j^2 / (2 S)                                                      (the shared -log(2 pi S)/2 dropped)
    K = P- / S,  omega^_j = omega^-_j + K e_j,            P = (1 - K) P-          (update)

The filter starts at the first reading with omega^_j = y and P = sigma_y^2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class SpeedFilter:
    """The shared part of the per-candidate filters (module docstring); ``omega`` is per candidate."""

    period_s: float
    inertia_kgm2: float
    torque_per_mu_nm: float
    sigma_y_rad_s: float            # motor-speed sensor noise
    q_var: float                    # process-noise variance per period, (rad/s)^2
    p_var: float = math.nan

    def open(self, y: float, n: int) -> np.ndarray:
        """Every candidate's speed estimate at the first reading."""
        self.p_var = self.sigma_y_rad_s ** 2
        return np.full(n, float(y))

    def gains(self, periods: int) -> tuple[float, float, float]:
        """(dt / J, S, K) of the next step, and P moved on to its value after the update."""
        p_pred = self.p_var + periods * self.q_var
        s = p_pred + self.sigma_y_rad_s ** 2
        k = p_pred / s
        self.p_var = (1.0 - k) * p_pred
        return periods * self.period_s / self.inertia_kgm2, s, k

    def step(self, omega: np.ndarray, m_prev: np.ndarray, m_new: np.ndarray, periods: int, torque_nm: float,
             y: float) -> np.ndarray:
        """Predict, weigh and update every candidate (in place on ``omega``); returns log L increments."""
        dt_j, s, k = self.gains(periods)
        omega += dt_j * (torque_nm - self.torque_per_mu_nm * 0.5 * (m_prev + m_new))     # predict
        e = y - omega                                                                      # innovation
        omega += k * e                                                                     # update
        return -0.5 / s * e * e                                                            # weigh
