"""The FFCC model M(v_s; theta) on numpy arrays, vectorised over parameter sets (particles).

theta = (lambda0, lambda1..n, tau1..n); v_s in km/h.  ``mu_model(v, theta)`` accepts theta of
shape (P,) or (N, P) and v of shape (S,), returning (S,) or (N, S).
"""
from __future__ import annotations

import numpy as np

PEAK_GRID_KMH = np.linspace(0.0, 10.0, 2001)


def n_terms(theta) -> int:
    return (np.shape(theta)[-1] - 1) // 2


def mu_model(creep_speed_kmh, theta):
    theta = np.asarray(theta, dtype=float)
    v = np.asarray(creep_speed_kmh, dtype=float)
    n = n_terms(theta)
    lam0 = theta[..., :1]
    lams = theta[..., 1:1 + n]
    taus = theta[..., 1 + n:]
    # (..., n, 1) * (S,) -> (..., n, S)
    with np.errstate(over="ignore", invalid="ignore"):
        terms = lams[..., :, None] * np.exp(taus[..., :, None] * v)
    return lam0 + terms.sum(axis=-2)


def jacobian(creep_speed_kmh, theta):
    """d mu / d theta at each sample, shape (S, P), for least_squares."""
    theta = np.asarray(theta, dtype=float)
    v = np.asarray(creep_speed_kmh, dtype=float)
    n = n_terms(theta)
    lams, taus = theta[1:1 + n], theta[1 + n:]
    e = np.exp(np.outer(v, taus))                     # (S, n)
    return np.hstack([np.ones((v.size, 1)), e, e * lams * v[:, None]])


def peak(theta, grid=PEAK_GRID_KMH) -> tuple[float, float]:
    """(creep speed km/h, mu) at the maximum of the curve on ``grid`` (refined parabolically)."""
    mu = mu_model(grid, theta)
    if not np.all(np.isfinite(mu)):
        return float("nan"), float("nan")
    i = int(np.argmax(mu))
    if 0 < i < grid.size - 1:
        y0, y1, y2 = mu[i - 1], mu[i], mu[i + 1]
        denom = y0 - 2 * y1 + y2
        if denom < 0:
            off = 0.5 * (y0 - y2) / denom
            h = grid[1] - grid[0]
            v = grid[i] + off * h
            return float(v), float(mu_model(np.array([v]), theta)[0])
    return float(grid[i]), float(mu[i])


def peak_two_terms(theta) -> tuple[np.ndarray, np.ndarray]:
    """(creep speed km/h, mu) of the maximum of two-term curves, in closed form, vectorised over
    theta (..., 5): mu'(v) = l1 t1 e^(t1 v) + l2 t2 e^(t2 v) = 0 at v = ln(-l2 t2 / (l1 t1)) / (t1 - t2).
    NaN where the curve has no interior maximum (the logarithm's argument <= 0, t1 = t2, or v < 0)."""
    th = np.asarray(theta, float)
    l0, l1, l2, t1, t2 = (th[..., i] for i in range(5))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v = np.log(-(l2 * t2) / (l1 * t1)) / (t1 - t2)
        v = np.where(np.isfinite(v) & (v >= 0.0), v, np.nan)
        mu = l0 + l1 * np.exp(t1 * v) + l2 * np.exp(t2 * v)
        # a maximum, not a minimum: mu'' < 0
        second = l1 * t1 * t1 * np.exp(t1 * v) + l2 * t2 * t2 * np.exp(t2 * v)
    ok = second < 0
    return np.where(ok, v, np.nan), np.where(ok, mu, np.nan)
