"""Nonlinear least squares (paper §3.2, eq. 6-8): trust-region fit, refit on all data as it grows.

Used alone it is the paper's first baseline; ``fit_curve`` is also the preliminary fit of the
particle-filter strategies.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from ..curve import jacobian, mu_model
from .base import Strategy

# Physically meaningful box for (lambda0, lambda_i, tau_i): decaying exponentials only.
LAMBDA_BOUND = 5.0
TAU_BOUNDS = (-10.0, -1e-3)


def parameter_bounds(n_terms: int, center=None, radius=None) -> tuple[np.ndarray, np.ndarray]:
    """The physical box for theta, intersected with ``center ± radius`` when a radius is given."""
    lo = np.r_[-1.0, np.full(n_terms, -LAMBDA_BOUND), np.full(n_terms, TAU_BOUNDS[0])]
    hi = np.r_[1.0, np.full(n_terms, LAMBDA_BOUND), np.full(n_terms, TAU_BOUNDS[1])]
    if radius is not None:
        lo, hi = np.maximum(lo, center - radius), np.minimum(hi, center + radius)
    return lo, hi


def fit_curve(creep_speed_kmh, mu_samples, theta0, radius=None) -> np.ndarray:
    """Trust-region-reflective least squares of M(v_s; theta) to mu^ samples, started at theta0.

    ``radius`` (P,): optionally keep the solution within theta0 +- radius (a bounded fit)."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    theta0 = np.asarray(theta0, float)
    lo, hi = parameter_bounds((theta0.size - 1) // 2, theta0, radius)
    start = np.clip(theta0, lo + 1e-9, hi - 1e-9)
    result = least_squares(lambda th: mu_model(v, th) - y, start, jac=lambda th: jacobian(v, th),
                           method="trf", bounds=(lo, hi), x_scale="jac", max_nfev=200)
    return result.x


class BoundedLm:
    """Projected Levenberg-Marquardt for small bounded least-squares problems, in plain numpy, one
    iteration per ``step()`` (so a caller can spread the iterations over several samples).

    ``fun(x) -> (r, J)`` (residuals (S,), Jacobian (S, P)).  Each iteration solves the damped
    normal equations (J^T J + lam diag(J^T J)) step = -J^T r on the free coordinates (a
    coordinate on a bound whose gradient pushes it outwards is held: the active set), clips the
    step into [lo, hi] and keeps it only if the cost falls (lam / 3), else lam * 4.  Stops when
    a kept step lowers the cost by less than ``rtol`` relative, after ``iterations``, or when lam
    exceeds 1e8.  A few tens of microseconds per iteration on the 5-parameter curve, against
    milliseconds for scipy's trust-region-reflective solver, whose per-call machinery dominates
    on a problem this small."""

    def __init__(self, fun, x0, lo, hi, iterations: int = 40, rtol: float = 1e-10):
        self.fun, self.lo, self.hi, self.rtol = fun, lo, hi, rtol
        self.x = np.clip(np.asarray(x0, float), lo, hi)
        self.left = int(iterations)
        self.lam = 1e-3
        self.r = None                   # residuals at x: evaluated by the first step (or ``start``)
        self.done = self.left <= 0

    def start(self) -> bool:
        """Evaluate the residuals at the starting point (the first ``step`` does it if needed)."""
        if self.r is None:
            self.r, self.jac = self.fun(self.x)
            self.cost = float(self.r @ self.r)
            self.done = self.done or not math.isfinite(self.cost)
        return self.done

    def step(self) -> bool:
        """One iteration; returns ``done``."""
        if self.r is None and self.start():
            return True
        if self.done:
            return True
        self.left -= 1
        x, r, jac, lo, hi = self.x, self.r, self.jac, self.lo, self.hi
        jt = jac.T
        g = jt @ r
        a = jt @ jac
        d = a.diagonal()
        a.flat[::a.shape[0] + 1] = d + self.lam * np.where(d > 0, d, 1e-12)
        at_lo, at_hi = x <= lo, x >= hi
        try:
            free = None
            if at_lo.any() or at_hi.any():      # active set: hold bound coordinates the gradient pushes out
                free = ~((at_lo & (g > 0)) | (at_hi & (g < 0)))
            if free is not None and not free.all():
                step = np.zeros_like(x)
                step[free] = np.linalg.solve(a[np.ix_(free, free)], -g[free])
            else:
                step = np.linalg.solve(a, -g)
        except np.linalg.LinAlgError:  # a singular step: more damping, tried again (Levenberg-Marquardt)
            self.lam *= 4.0
            self.done = self.left <= 0
            return self.done
        xn = np.minimum(np.maximum(x + step, lo), hi)
        rn, jn = self.fun(xn)
        cn = float(rn @ rn)
        if math.isfinite(cn) and cn < self.cost:
            converged = self.cost - cn <= self.rtol * self.cost
            self.x, self.r, self.jac, self.cost = xn, rn, jn, cn
            self.lam = max(self.lam / 3.0, 1e-9)
            self.done = converged
        else:
            self.lam *= 4.0
            self.done = self.lam > 1e8
        self.done = self.done or self.left <= 0
        return self.done


def bounded_lm(fun, x0, lo, hi, iterations: int = 40, rtol: float = 1e-10):
    """``BoundedLm`` run to the end; returns x."""
    lm = BoundedLm(fun, x0, lo, hi, iterations, rtol)
    lm.start()
    while not lm.done:
        lm.step()
    return lm.x


def fit_curve_lm(creep_speed_kmh, mu_samples, theta0, radius=None, iterations: int = 40) -> np.ndarray:
    """``fit_curve`` by ``bounded_lm``: the same problem and bounds, solved in numpy (cheap enough
    for the TCU's sampling period; see ``hil bench identify`` for what it changes)."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    theta0 = np.asarray(theta0, float)
    n = (theta0.size - 1) // 2
    lo, hi = parameter_bounds(n, theta0, radius)
    jac = np.empty((v.size, theta0.size))
    jac[:, 0] = 1.0

    def fun(th):
        e = np.exp(np.outer(v, th[1 + n:]))          # (S, n)
        jac[:, 1:1 + n] = e
        jac[:, 1 + n:] = e * th[1:1 + n] * v[:, None]
        return th[0] + e @ th[1:1 + n] - y, jac.copy()

    return bounded_lm(fun, theta0, lo, hi, iterations)


def _grid_lattice(theta0, radius, grid: int):
    """Bounds (theta0 +- radius within parameter_bounds) and the (G, n) tau lattice of fit_curve_grid."""
    theta0 = np.asarray(theta0, float)
    n = (theta0.size - 1) // 2
    lo, hi = parameter_bounds(n, theta0, radius)
    axes = [np.linspace(lo[1 + n + i], hi[1 + n + i], grid) for i in range(n)]
    taus = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n)       # (G, n)
    return n, lo, hi, taus


def _solve_spd(a, b):
    """x with a x = b for a batch of symmetric positive definite (G, k, k) systems (b: (G, k)).
    k = 3 (the two-term curve's lambdas) by an unrolled LDL^T on (G,) arrays: elementwise ufuncs,
    which the filter step keeps warm, instead of np.linalg.solve's heavier batched path (costly when
    it runs once per slip, on cold code); other k: np.linalg."""
    if a.shape[-1] != 3:
        return np.linalg.solve(a, b[..., None])[..., 0]
    a00, a10, a20, a11, a21, a22 = a[:, 0, 0], a[:, 1, 0], a[:, 2, 0], a[:, 1, 1], a[:, 2, 1], a[:, 2, 2]
    l10 = a10 / a00
    l20 = a20 / a00
    d1 = a11 - l10 * a10
    c21 = a21 - l20 * a10
    l21 = c21 / d1
    d2 = a22 - l20 * a20 - l21 * c21
    z0 = b[:, 0]
    z1 = b[:, 1] - l10 * z0
    z2 = b[:, 2] - l20 * z0 - l21 * z1
    x = np.empty_like(b)
    x[:, 2] = z2 / d2
    x[:, 1] = z1 / d1 - l21 * x[:, 2]
    x[:, 0] = z0 / a00 - l10 * x[:, 1] - l20 * x[:, 2]
    return x


def _grid_best(a, b, cost_of, taus, lo, hi, n):
    """Per lattice point the linear lambda from the normal equations a lam = b (+ one active-set
    pass for the lambda bounds); the lattice point of least ``cost_of(lam)`` -> (lambda, tau)."""
    eye = np.eye(1 + n)
    ar = a + (1e-12 * a.diagonal(axis1=1, axis2=2).sum(axis=1))[:, None, None] * eye   # a + ridge
    lam = _solve_spd(ar, b)                                                          # (G, 1+n)
    llo, lhi = lo[:1 + n], hi[:1 + n]
    out = (lam < llo) | (lam > lhi)
    if out.any():                                  # one active-set pass: clip, re-solve the free ones
        fixed = np.minimum(np.maximum(lam, llo), lhi)
        free = ~out
        held = np.where(out, fixed, 0.0)
        bb = np.where(free, b - (a @ held[..., None])[..., 0], 0.0)
        aa = np.where(free[:, :, None] & free[:, None, :], ar, 0.0) + eye * out[:, :, None]
        lam = np.where(free, _solve_spd(aa, bb), fixed)
        lam = np.minimum(np.maximum(lam, llo), lhi)
    cost = cost_of(lam)
    cost[~np.isfinite(cost)] = np.inf
    best = int(np.argmin(cost))
    return np.concatenate((lam[best], taus[best]))


def _polish_fun(v, target, K, n: int):
    """(r, J) of the LM polish: M(v; theta) (or K @ M) minus the target."""
    jac = np.empty((v.size, 2 * n + 1))
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

    return fun


def fit_curve_grid(creep_speed_kmh, mu_samples, theta0, radius, grid: int = 5, polish: int = 3,
                   transform=None, offset=None, job: bool = False):
    """The bounded fit of ``fit_curve`` by variable projection on a grid, then a short LM polish.

    For fixed tau the model is linear in lambda, so on a ``grid`` x ``grid`` lattice of tau inside
    the box (theta0 +- radius) each lambda is one batched 3x3 solve (coordinates that land outside
    their bounds are clipped and the others re-solved once: an active-set pass).  The best lattice
    point starts ``polish`` iterations of ``bounded_lm`` on all parameters.  A few hundred
    microseconds in numpy and no worse a minimum than scipy's solver on the bench's first windows
    (the problem is a flat valley: many thetas fit six samples equally well).  ``GridAccumulator``
    builds the same lattice sample by sample.

    ``transform`` (S, S) and ``offset`` (S,): fit ``transform @ M(v; theta) + offset`` instead of
    M (the observer-aware model's linear map).

    ``job``: return the lattice's result as a ``BoundedLm`` whose ``step()`` runs one polish
    iteration (``.x`` when ``.done``), so the polish can be spread over several samples."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    n, lo, hi, taus = _grid_lattice(theta0, radius, grid)
    K = None if transform is None else np.asarray(transform, float)
    target = y if offset is None else y - np.asarray(offset, float)
    phi = np.concatenate([np.ones((taus.shape[0], v.size, 1)),
                          np.exp(taus[:, None, :] * v[None, :, None])], axis=2)      # (G, S, 1+n)
    kphi = phi if K is None else np.einsum("st,gtj->gsj", K, phi)                    # (G, S, 1+n)
    a = np.einsum("gsi,gsj->gij", kphi, kphi)
    b = np.einsum("gsi,s->gi", kphi, target)

    def cost_of(lam):
        resid = np.einsum("gsj,gj->gs", kphi, lam) - target[None, :]
        return np.einsum("gs,gs->g", resid, resid)

    start = _grid_best(a, b, cost_of, taus, lo, hi, n)
    if polish <= 0:
        return start if job is False else _Done(start)
    fun = _polish_fun(v, target, K, n)
    if job:
        return BoundedLm(fun, start, lo, hi, polish)
    return bounded_lm(fun, start, lo, hi, polish)


_NO_TRANSFORM = np.zeros((0, 0))      # kernels.bounded_lm's "no transform" (the plain curve model)


class GridAccumulator:
    """``fit_curve_grid``'s lattice built sample by sample: ``add`` one sample's rank-one update
    of every lattice point's normal equations as it arrives (a few microseconds), ``job`` at the
    window's end solves them (the least-squares cost from the same sums: |t|^2 - 2 lam.b +
    lam.A lam) and returns the LM polish as a ``BoundedLm`` to step later.  The same problem as
    ``fit_curve_grid(..., job=True)``, equal up to rounding.  ``size``: the most samples added."""

    def __init__(self, theta0, radius, grid: int, polish: int, size: int, compiled: bool = False):
        self.compiled = False               # job() solves and polishes at once (identifier/kernels.py)
        if compiled:
            from .. import kernels          # here: numba's import only where it is used
            self.compiled = kernels.AVAILABLE
        self.n, self.lo, self.hi, self.taus = _grid_lattice(theta0, radius, grid)
        g, p1 = self.taus.shape[0], self.n + 1
        self.phi = np.ones((size, g, p1))
        self.a = np.zeros((g, p1, p1))
        self.b = np.zeros((g, p1))
        self.tt = 0.0
        self.count = 0
        self.size = int(size)
        self.polish = int(polish)

    def add(self, creep_speed_kmh: float, target: float, k_row=None) -> None:
        """One sample; ``k_row`` (count + 1,): its row of the transform (observer-aware model)."""
        ph = self.phi[self.count]
        if self.compiled and k_row is None:        # one compiled pass instead of several numpy calls
            from .. import kernels
            kernels.grid_add(self.taus, float(creep_speed_kmh), float(target), ph, self.a, self.b)
            self.tt += target * target
            self.count += 1
            return
        np.exp(self.taus * creep_speed_kmh, out=ph[:, 1:])
        if k_row is not None:
            c = self.count + 1
            ph = (np.asarray(k_row, float) @ self.phi[:c].reshape(c, -1)).reshape(ph.shape)
        self.a += ph[:, :, None] * ph[:, None, :]
        self.b += ph * target
        self.tt += target * target
        self.count += 1

    def job(self, creep_speed_kmh, targets, transform=None):
        """The lattice's best point, then the polish on (v, targets) as a ``BoundedLm``."""
        def cost_of(lam):
            q = (self.a * lam[:, None, :]).sum(axis=2) - 2.0 * self.b       # A lam - 2 b
            return (lam * q).sum(axis=1) + self.tt

        if self.compiled:           # the lattice now, the whole polish as one step
            from .. import kernels
            start = kernels.grid_best(self.a, self.b, self.tt, self.taus, self.lo, self.hi)
            k = _NO_TRANSFORM if transform is None else np.ascontiguousarray(transform, dtype=float)
            return _CompiledPolish(start, self.lo, self.hi, np.asarray(creep_speed_kmh, float),
                                   np.asarray(targets, float), k, self.polish)
        start = _grid_best(self.a, self.b, cost_of, self.taus, self.lo, self.hi, self.n)
        if self.polish <= 0:
            return _Done(start)
        K = None if transform is None else np.asarray(transform, float)
        fun = _polish_fun(np.asarray(creep_speed_kmh, float), np.asarray(targets, float), K, self.n)
        return BoundedLm(fun, start, self.lo, self.hi, self.polish)


class _CompiledPolish:
    """The LM polish of ``GridAccumulator.job`` by ``kernels.bounded_lm``: its first ``step()`` runs
    all the iterations in one compiled call (so a caller can put the lattice and the polish on two
    samples); ``.x`` is the lattice's point until then."""

    def __init__(self, start, lo, hi, v, targets, transform, iterations: int):
        self.x, self._args, self._iterations = start, (lo, hi, v, targets, transform), iterations
        self.done = iterations <= 0

    def step(self) -> bool:
        if not self.done:
            from .. import kernels
            lo, hi, v, targets, transform = self._args
            self.x = kernels.bounded_lm(self.x, lo, hi, v, targets, transform, self._iterations, 1e-10)
            self.done = True
        return True


class _Done:
    """A finished job (``fit_curve_grid(..., job=True)`` without polish)."""

    done = True

    def __init__(self, x):
        self.x = x

    def step(self) -> bool:
        return True


class NllsStrategy(Strategy):
    """Refit on every sample so far, at the end of every window (the paper's NLLS baseline)."""

    name = "nlls"

    def correct(self, window_v, window_mu):
        v, mu = self.data()
        theta = fit_curve(v, mu, self.theta)
        self._fit_cov = fit_covariance(v, mu, theta)
        return theta

    def peak_intervals(self, level: float):
        """A confidence interval from the fit (``fit_covariance``, ``peak_confidence``)."""
        cov = getattr(self, "_fit_cov", None)
        if cov is None or np.size(self.theta) != 5:
            return super().peak_intervals(level)
        return peak_confidence(self.theta, cov, level)


def fit_covariance(creep_speed_kmh, mu_samples, theta) -> np.ndarray | None:
    """The least-squares estimate's covariance, s^2 (J^T J)^+ with s^2 = SSR / (S - P) (the usual
    linearisation at the optimum; None with no residual degrees of freedom)."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    theta = np.asarray(theta, float)
    dof = v.size - theta.size
    if dof <= 0:
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        r = y - mu_model(v, theta)
        jac = jacobian(v, theta)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(jac))):
        return None
    return float(r @ r) / dof * np.linalg.pinv(jac.T @ jac)


def peak_confidence(theta, cov, level: float):
    """Peak mu and peak creep intervals by the delta method: the closed-form peak's gradient
    (central differences) through ``cov``, +- z sd with z the normal quantile of ``level``."""
    from statistics import NormalDist

    from ..curve import peak_two_terms

    theta = np.asarray(theta, float)
    z = NormalDist().inv_cdf(0.5 * (1.0 + level))
    steps = 1e-6 * np.maximum(np.abs(theta), 1e-3)
    pts = np.vstack([theta + np.diag(steps), theta - np.diag(steps), theta[None, :]])
    v, mu = peak_two_terms(pts)
    out = []
    for f in (mu, v):
        grad = (f[:5] - f[5:10]) / (2.0 * steps)
        sd = math.sqrt(max(float(grad @ cov @ grad), 0.0)) if np.all(np.isfinite(grad)) else math.nan
        centre = float(f[10])
        out.append((centre - z * sd, centre + z * sd) if math.isfinite(sd) and math.isfinite(centre)
                   else (math.nan, math.nan))
    # a linearisation far from the data can reach past what is physical: say "anywhere there" instead
    (m0, m1), (c0, c1) = out
    return (max(m0, 0.0), min(m1, 1.0)), (max(c0, 0.0), min(c1, PEAK_CREEP_MAX_KMH))


#: the largest peak creep an interval reports (curve.PEAK_GRID_KMH's end would do; 30 km/h as plant.friction)
PEAK_CREEP_MAX_KMH = 30.0
