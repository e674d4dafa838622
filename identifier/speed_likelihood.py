"""The likelihood of the motor-speed readings under a candidate friction curve: one Kalman filter
per candidate, the numpy reference (``identifier/kernels.py`` has its compiled twin for the
``bayes`` strategy; the offline oracle of ``hil bench identify`` runs this one on many candidates).

The wheelset between two readings, the torque held (paper eq. A, J = J_eq, c = torque per unit mu),
with an optional slowly wandering offset delta of the true mu from the candidate's curve (a model
discrepancy: a curve of another form than the candidate's differs from it smoothly, so the offset
is a random walk, not white noise):

    omega(k+1) = omega(k) + (dt / J) (T_e(k) - c (mbar(k) + delta(k))) + w(k),   w ~ N(0, q dt / T)
    delta(k+1) = delta(k) + d(k),                                     d ~ N(0, q_delta dt / T)
    mbar(k)    = (M(v_s(k)) + M(v_s(k+1))) / 2                       (trapezoid: mu changes within the period)
    y(k)       = omega(k) + n(k),                                     n ~ N(0, sigma_y^2)

Kalman filter per candidate j on x = (omega, delta), F = [[1, -b], [0, 1]], b = c dt / J, H = [1, 0]
(F, Q, H and so P, S and K are the same for every candidate: they are shared scalars):

    omega^-_j = omega^_j + (dt / J) (T_e - c (mbar_j + delta^_j))      P- = F P F^T + Q      (predict)
    e_j = y - omega^-_j                                                 S = P-_00 + sigma_y^2 (innovation)
    log L_j += -e_j^2 / (2 S)                                            (the shared -log(2 pi S)/2 dropped)
    K = P-_{:,0} / S,  omega^_j = omega^-_j + K_0 e_j,  delta^_j += K_1 e_j,  P = (I - K H) P-   (update)

The filter starts at the first reading with omega^_j = y, delta^_j = 0, P = diag(sigma_y^2, 0).  With
q_delta = 0 (the default) delta stays 0 and this is the one-state filter of the wheelset's speed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class SpeedFilter:
    """The shared part of the per-candidate filters (module docstring); ``omega`` (and ``delta``) are
    per candidate."""

    period_s: float
    inertia_kgm2: float
    torque_per_mu_nm: float
    sigma_y_rad_s: float            # motor-speed sensor noise
    q_var: float                    # process-noise variance per period, (rad/s)^2
    p_var: float = math.nan         # P_00: the speed estimate's variance
    q_delta_var: float = 0.0        # the offset's random-walk variance per period, mu^2
    p_cross: float = 0.0            # P_01
    p_delta: float = 0.0            # P_11

    def open(self, y: float, n: int) -> np.ndarray:
        """Every candidate's speed estimate at the first reading (the offsets start at 0)."""
        self.p_var = self.sigma_y_rad_s ** 2
        self.p_cross = self.p_delta = 0.0
        return np.full(n, float(y))

    def gains(self, periods: int) -> tuple[float, float, float, float]:
        """(dt / J, S, K_0, K_1) of the next step, and P moved on to its value after the update."""
        a = periods * self.period_s / self.inertia_kgm2
        b = a * self.torque_per_mu_nm
        p00 = self.p_var - 2.0 * b * self.p_cross + b * b * self.p_delta + periods * self.q_var      # F P F^T + Q
        p01 = self.p_cross - b * self.p_delta
        p11 = self.p_delta + periods * self.q_delta_var
        s = p00 + self.sigma_y_rad_s ** 2
        k0, k1 = p00 / s, p01 / s
        self.p_var, self.p_cross, self.p_delta = (1.0 - k0) * p00, (1.0 - k0) * p01, p11 - k1 * p01   # (I - K H) P-
        return a, s, k0, k1

    def step(self, omega: np.ndarray, m_prev: np.ndarray, m_new: np.ndarray, periods: int, torque_nm: float,
             y: float, delta: np.ndarray | None = None) -> np.ndarray:
        """Predict, weigh and update every candidate (in place on ``omega`` and ``delta``; ``delta``
        None: no offset, q_delta must be 0); returns log L increments."""
        dt_j, s, k0, k1 = self.gains(periods)
        mbar = 0.5 * (m_prev + m_new) if delta is None else 0.5 * (m_prev + m_new) + delta
        omega += dt_j * (torque_nm - self.torque_per_mu_nm * mbar)                         # predict
        e = y - omega                                                                      # innovation
        omega += k0 * e                                                                    # update
        if delta is not None:
            delta += k1 * e
        elif self.q_delta_var:
            raise ValueError("SpeedFilter.step: q_delta_var > 0 needs the offsets (delta)")
        return -0.5 / s * e * e                                                            # weigh
