"""Nonlinear least squares (paper §3.2, eq. 6-8): trust-region fit, refit on all data as it grows.

Used alone it is the paper's first baseline; ``fit_curve`` is also the preliminary fit of the
particle-filter strategies.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ..curve import jacobian, mu_model
from .base import Strategy

# Physically meaningful box for (lambda0, lambda_i, tau_i): decaying exponentials only.
LAMBDA_BOUND = 5.0
TAU_BOUNDS = (-10.0, -1e-3)


def parameter_bounds(n_terms: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.r_[-1.0, np.full(n_terms, -LAMBDA_BOUND), np.full(n_terms, TAU_BOUNDS[0])]
    hi = np.r_[1.0, np.full(n_terms, LAMBDA_BOUND), np.full(n_terms, TAU_BOUNDS[1])]
    return lo, hi


def fit_curve(creep_speed_kmh, mu_samples, theta0, radius=None) -> np.ndarray:
    """Trust-region-reflective least squares of M(v_s; theta) to mu^ samples, started at theta0.

    ``radius`` (P,): optionally keep the solution within theta0 +- radius (a bounded fit)."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    theta0 = np.asarray(theta0, float)
    lo, hi = parameter_bounds((theta0.size - 1) // 2)
    if radius is not None:
        lo, hi = np.maximum(lo, theta0 - radius), np.minimum(hi, theta0 + radius)
    start = np.clip(theta0, lo + 1e-9, hi - 1e-9)
    result = least_squares(lambda th: mu_model(v, th) - y, start, jac=lambda th: jacobian(v, th),
                           method="trf", bounds=(lo, hi), x_scale="jac", max_nfev=200)
    return result.x


class NllsStrategy(Strategy):
    """Refit on every sample so far, at the end of every window (the paper's NLLS baseline)."""

    name = "nlls"

    def correct(self, window_v, window_mu):
        v, mu = self.data()
        return fit_curve(v, mu, self.theta)
