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


def standard_error(creep_speed_kmh, mu_samples, theta) -> float:
    """SE of eq. 29 on the current window: sqrt(sum(resid^2) / (L - 2n - 1))."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    n = (len(theta) - 1) // 2
    dof = v.size - 2 * n - 1
    if dof <= 0:
        return math.inf
    resid = y - mu_model(v, theta)
    return float(np.sqrt(np.sum(resid ** 2) / dof))


def inside_confidence_band(creep_speed_kmh, mu_samples, theta, se: float, c_lw: float, c_up: float) -> bool:
    """Gamma = 1 when every new sample lies in [M - c_lw*SE, M + c_up*SE] (eq. 28-31)."""
    m = mu_model(np.asarray(creep_speed_kmh, float), theta)
    y = np.asarray(mu_samples, float)
    return bool(np.all((y >= m - c_lw * se) & (y <= m + c_up * se)))
