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


def bounded_lm(fun, x0, lo, hi, iterations: int = 40, rtol: float = 1e-10):
    """Projected Levenberg-Marquardt for small bounded least-squares problems, in plain numpy.

    ``fun(x) -> (r, J)`` (residuals (S,), Jacobian (S, P)).  Each iteration solves the damped
    normal equations (J^T J + lam diag(J^T J)) step = -J^T r on the free coordinates (a
    coordinate on a bound whose gradient pushes it outwards is held: the active set), clips the
    step into [lo, hi] and keeps it only if the cost falls (lam / 3), else lam * 4.  Stops when
    a kept step lowers the cost by less than ``rtol`` relative.  A few tens of microseconds per
    iteration on the 5-parameter curve, against milliseconds for scipy's trust-region-reflective
    solver, whose per-call machinery dominates on a problem this small."""
    x = np.clip(np.asarray(x0, float), lo, hi)
    r, jac = fun(x)
    cost = float(r @ r)
    if not np.isfinite(cost):
        return x
    lam = 1e-3
    diag = np.diag_indices(x.size)
    for _ in range(iterations):
        g = jac.T @ r
        a = jac.T @ jac
        d = a[diag]
        a[diag] += lam * np.where(d > 0, d, 1e-12)
        at_lo, at_hi = x <= lo, x >= hi
        try:
            if at_lo.any() or at_hi.any():      # active set: hold bound coordinates the gradient pushes out
                free = ~((at_lo & (g > 0)) | (at_hi & (g < 0)))
                step = np.zeros_like(x)
                step[free] = np.linalg.solve(a[np.ix_(free, free)], -g[free])
            else:
                step = np.linalg.solve(a, -g)
        except np.linalg.LinAlgError:
            lam *= 4.0
            continue
        xn = np.clip(x + step, lo, hi)
        rn, jn = fun(xn)
        cn = float(rn @ rn)
        if np.isfinite(cn) and cn < cost:
            done = cost - cn <= rtol * cost
            x, r, jac, cost = xn, rn, jn, cn
            lam = max(lam / 3.0, 1e-9)
            if done:
                break
        else:
            lam *= 4.0
            if lam > 1e8:
                break
    return x


def fit_curve_lm(creep_speed_kmh, mu_samples, theta0, radius=None, iterations: int = 40) -> np.ndarray:
    """``fit_curve`` by ``bounded_lm``: the same problem and bounds, solved in numpy (cheap enough
    for the TCU's sampling period; see ``hil bench identify`` for what it changes)."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    theta0 = np.asarray(theta0, float)
    n = (theta0.size - 1) // 2
    lo, hi = parameter_bounds(n)
    if radius is not None:
        lo, hi = np.maximum(lo, theta0 - radius), np.minimum(hi, theta0 + radius)
    jac = np.empty((v.size, theta0.size))
    jac[:, 0] = 1.0

    def fun(th):
        e = np.exp(np.outer(v, th[1 + n:]))          # (S, n)
        jac[:, 1:1 + n] = e
        jac[:, 1 + n:] = e * th[1:1 + n] * v[:, None]
        return th[0] + e @ th[1:1 + n] - y, jac.copy()

    return bounded_lm(fun, theta0, lo, hi, iterations)


def fit_curve_grid(creep_speed_kmh, mu_samples, theta0, radius, grid: int = 5, polish: int = 3,
                   transform=None, offset=None) -> np.ndarray:
    """The bounded fit of ``fit_curve`` by variable projection on a grid, then a short LM polish.

    For fixed tau the model is linear in lambda, so on a ``grid`` x ``grid`` lattice of tau inside
    the box (theta0 +- radius) each lambda is one batched 3x3 solve (coordinates that land outside
    their bounds are clipped and the others re-solved once: an active-set pass).  The best lattice
    point starts ``polish`` iterations of ``bounded_lm`` on all parameters.  A few hundred
    microseconds in numpy and no worse a minimum than scipy's solver on the bench's first windows
    (the problem is a flat valley: many thetas fit six samples equally well).

    ``transform`` (S, S) and ``offset`` (S,): fit ``transform @ M(v; theta) + offset`` instead of
    M (the observer-aware model's linear map)."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    theta0 = np.asarray(theta0, float)
    n = (theta0.size - 1) // 2
    lo, hi = parameter_bounds(n)
    if radius is not None:
        lo, hi = np.maximum(lo, theta0 - radius), np.minimum(hi, theta0 + radius)
    K = None if transform is None else np.asarray(transform, float)
    target = y if offset is None else y - np.asarray(offset, float)
    axes = [np.linspace(lo[1 + n + i], hi[1 + n + i], grid) for i in range(n)]
    taus = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n)       # (G, n)
    phi = np.concatenate([np.ones((taus.shape[0], v.size, 1)),
                          np.exp(taus[:, None, :] * v[None, :, None])], axis=2)      # (G, S, 1+n)
    kphi = phi if K is None else np.einsum("st,gtj->gsj", K, phi)                    # (G, S, 1+n)
    a = np.einsum("gsi,gsj->gij", kphi, kphi)
    b = np.einsum("gsi,s->gi", kphi, target)
    ridge = 1e-12 * np.trace(a, axis1=1, axis2=2)[:, None, None] * np.eye(1 + n)
    lam = np.linalg.solve(a + ridge, b[..., None])[..., 0]                           # (G, 1+n)
    llo, lhi = lo[:1 + n], hi[:1 + n]
    out = (lam < llo) | (lam > lhi)
    if out.any():                                  # one active-set pass: clip, re-solve the free ones
        fixed = np.clip(lam, llo, lhi)
        free = ~out
        bb = b - np.einsum("gij,gj->gi", a, np.where(free, 0.0, fixed))
        aa = np.where(free[:, :, None] & free[:, None, :], a, 0.0) + np.eye(1 + n) * (~free)[:, :, None] + ridge
        lam = np.where(free, np.linalg.solve(aa, np.where(free, bb, 0.0)[..., None])[..., 0], fixed)
        lam = np.clip(lam, llo, lhi)
    resid = np.einsum("gsj,gj->gs", kphi, lam) - target[None, :]
    cost = np.einsum("gs,gs->g", resid, resid)
    cost[~np.isfinite(cost)] = np.inf
    best = int(np.argmin(cost))
    start = np.r_[lam[best], taus[best]]
    if polish <= 0:
        return start
    jac = np.empty((v.size, theta0.size))
    jac[:, 0] = 1.0

    vcol = v[:, None]

    def fun(th):
        e = np.exp(vcol * th[1 + n:])
        jac[:, 1:1 + n] = e
        jac[:, 1 + n:] = e * th[1:1 + n] * vcol
        m = e @ th[1:1 + n] + th[0]
        if K is None:
            return m - target, jac.copy()
        return K @ m - target, K @ jac

    return bounded_lm(fun, start, lo, hi, polish)


class NllsStrategy(Strategy):
    """Refit on every sample so far, at the end of every window (the paper's NLLS baseline)."""

    name = "nlls"

    def correct(self, window_v, window_mu):
        v, mu = self.data()
        return fit_curve(v, mu, self.theta)
