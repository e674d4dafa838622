"""Multi-level evaluation (paper §3.5, eq. 25-31): preliminary evaluation, then a confidence check
of the candidate curve on the *next* window of samples."""
from __future__ import annotations

import math

import numpy as np

from .curve import mu_model


def j_ef(estimate, previous) -> float:
    """J_EF(Q) = ||chi^_Q - chi^_{Q-1}||^2 (eq. 25-26)."""
    d = np.asarray(estimate, float) - np.asarray(previous, float)
    return float(np.dot(d, d))


#: windows up to this many samples are evaluated with Python floats: a window is L ~ 6 samples, where
#: a handful of numpy calls on 6-element arrays cost several times the arithmetic (this runs on the
#: TCU's sample that closes a window, the costliest one)
SMALL_WINDOW = 32


def _curve(v, theta) -> list[float] | np.ndarray:
    """M(v_s; theta) at each sample: a list for small windows, else a numpy array."""
    if len(v) > SMALL_WINDOW:
        return mu_model(np.asarray(v, float), theta)
    th = np.asarray(theta, float).tolist()
    n = (len(th) - 1) // 2
    out = []
    for vk in np.asarray(v, float).tolist():
        m = 0.0
        for i in range(n):
            try:
                m += th[1 + i] * math.exp(th[1 + n + i] * vk)
            except OverflowError:                     # as numpy: exp -> inf
                m += th[1 + i] * math.inf
        out.append(m + th[0])
    return out


def standard_error(creep_speed_kmh, mu_samples, theta) -> float:
    """SE of eq. 29 on the current window: sqrt(sum(resid^2) / (L - 2n - 1))."""
    n = (len(theta) - 1) // 2
    dof = len(creep_speed_kmh) - 2 * n - 1
    if dof <= 0:
        return math.inf
    m = _curve(creep_speed_kmh, theta)
    ss = sum((y - mk) ** 2 for y, mk in zip(np.asarray(mu_samples, float).tolist(), m))
    return math.sqrt(ss / dof) if ss == ss else math.nan


def inside_confidence_band(creep_speed_kmh, mu_samples, theta, se: float, c_lw: float, c_up: float) -> bool:
    """Gamma = 1 when every new sample lies in [M - c_lw*SE, M + c_up*SE] (eq. 28-31)."""
    m = _curve(creep_speed_kmh, theta)
    return all(mk - c_lw * se <= y <= mk + c_up * se for y, mk in zip(np.asarray(mu_samples, float).tolist(), m))
