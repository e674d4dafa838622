"""Load-torque observer (paper eq. 4-5, Appendix A), discretised by forward Euler.

    x = [omega_m, T_L],  A = [[0, -1/J_eq], [0, 0]],  B = [1/J_eq, 0],  C = [1, 0]
    x(k+1) = (I + A T) x(k) + B T T_e(k) + H T (y(k) - C x(k))

Gains by pole placement: the error dynamics have characteristic polynomial
``s^2 + h_w s - h_TL / J_eq``; placing a double pole at ``s = -p`` gives

    h_w = 2 p,    h_TL = -J_eq p^2.

With Euler at period T the discrete poles are ``z = 1 - p T``, so ``p T < 1`` keeps them real and
inside the unit circle (``p T = 1`` is dead-beat).  A double pole at ``p`` makes T^_L follow a
ramp in T_L with a lag of ``2 / p`` seconds: the pairing of mu^ with creep speed is biased by that
lag unless it is compensated (see ``IdentifierSettings.lag_compensation``).
"""
from __future__ import annotations

import numpy as np


class LoadTorqueObserver:
    def __init__(self, equivalent_inertia_kgm2: float, period_s: float, pole_rad_s: float):
        if not (0 < pole_rad_s * period_s <= 1):
            raise ValueError(f"observer pole {pole_rad_s} rad/s with period {period_s} s: need 0 < p*T <= 1")
        self.inertia = equivalent_inertia_kgm2
        self.period_s = period_s
        self.pole_rad_s = pole_rad_s
        self.gain_speed = 2.0 * pole_rad_s                              # h_w   [1/s]
        self.gain_torque = -equivalent_inertia_kgm2 * pole_rad_s ** 2   # h_TL  [N·m·s/rad]
        self.speed_rad_s = np.nan
        self.load_torque_nm = np.nan

    @property
    def lag_s(self) -> float:
        """Ramp-following lag of the load-torque estimate, 2/p."""
        return 2.0 / self.pole_rad_s

    def state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C) of ``update`` as one linear system, for running it over a whole record at once
        (``hil/gap/model.ObserverReplica``): state x = [omega^, T^_L], inputs u = [T_e, y], output T^_L,

            x(k+1) = A x(k) + B u(k),   A = [[1 - T h_w, -T / J], [-T h_TL, 1]],
            B = [[T / J, T h_w], [0, T h_TL]],   C = [0, 1]."""
        T, J, h_w, h_tl = self.period_s, self.inertia, self.gain_speed, self.gain_torque
        A = np.array([[1 - T * h_w, -T / J], [-T * h_tl, 1.0]])
        B = np.array([[T / J, T * h_w], [0.0, T * h_tl]])
        return A, B, np.array([[0.0, 1.0]])

    def reset(self, speed_rad_s: float, load_torque_nm: float) -> None:
        self.speed_rad_s = float(speed_rad_s)
        self.load_torque_nm = float(load_torque_nm)

    def update(self, measured_speed_rad_s: float, torque_nm: float) -> float:
        """Advance one period with y(k) and T_e(k); returns the estimate T^_L(k) used for mu^(k).

        The estimate returned is the one *before* the update, i.e. x^(k), which is what eq. 5 uses
        at instant k; the state then moves on to x^(k+1).
        """
        if np.isnan(self.speed_rad_s):
            self.reset(measured_speed_rad_s, torque_nm)
        estimate = self.load_torque_nm
        innovation = measured_speed_rad_s - self.speed_rad_s
        T = self.period_s
        self.speed_rad_s += T * ((torque_nm - self.load_torque_nm) / self.inertia + self.gain_speed * innovation)
        self.load_torque_nm += T * self.gain_torque * innovation
        return estimate
