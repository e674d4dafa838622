"""Small particle-filter pieces for the MDIPF (paper §3.3-3.4, Appendix B), each on a whole cloud.

Particles are error vectors chi = (xi0, xi1..n, gamma1..n), an (N, P) array added to the current
curve parameters theta (P = 2n + 1).  Every function is vectorised over particles; none loops over
them in Python.  The pieces, in the order a filter step uses them:

- ``correlation_transition``  Theta(k-1): the Pearson correlation of the cloud's dimensions,
  made stable (the paper leaves this open; see ``STABILISERS``).
- ``propagate``               chi(k) = Theta chi(k-1) + beta,  beta ~ N(0, diag(B)).
- ``log_likelihood``          log p(Z | chi) for Z = M_cor(v_s) + phi,  phi ~ N(0, G).
- ``normalise``               weights from log weights, NaN/inf safe.
- ``ess``, ``resample``       effective sample size; systematic / multinomial / stratified resampling.
- ``project_to_box``          the dynamic projection domain: particles outside [lo, hi] moved inside
  by minimising -log p(chi~ - chi_out) - log p(Z - M_cor(chi~)) over the box.

The strategies' hot path (identifier/strategies/mdipf.py) uses ``rownorm_transition`` and
``systematic_counts_resample``: the same operations as ``correlation_transition(..., "rownorm")``
and ``resample(..., "systematic")`` up to rounding, in fewer numpy calls.
"""
from __future__ import annotations

import numpy as np

from .curve import mu_model

STABILISERS = ("rownorm", "spectral", "raw", "identity")
RESAMPLERS = ("systematic", "multinomial", "stratified")
PROJECTORS = ("map", "clip")


def weighted_correlation(particles: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted Pearson correlation matrix (P, P) of the cloud; a dimension with no spread
    correlates only with itself (1 on the diagonal, 0 elsewhere).

    Works on ``particles.T`` (a contiguous (P, N) view when the strategy keeps its (N, P) cloud in
    Fortran order), so every pass over the cloud is over contiguous rows."""
    x = particles.T
    d = x - (x @ weights)[:, None]
    cov = (d * weights) @ d.T
    sd = np.sqrt(np.maximum(cov.diagonal(), 0.0))
    inv = np.divide(1.0, sd, out=np.zeros_like(sd), where=sd > 1e-300)
    corr = cov * inv[:, None] * inv[None, :]
    np.fill_diagonal(corr, 1.0)
    return np.clip(corr, -1.0, 1.0, out=corr)


def rownorm_transition(xt: np.ndarray, weights: np.ndarray, d: np.ndarray, dw: np.ndarray) -> np.ndarray:
    """``correlation_transition(xt.T, weights, "rownorm")`` up to rounding, in fewer numpy calls
    (the filter step's hot path): ``xt`` is the (P, N) contiguous cloud, ``d`` and ``dw`` are
    (P, N) scratch buffers.  Row-normalising the correlation R_ij = C_ij s_i s_j (s = 1/sd) gives
    C_ij s_j / sum_k |C_ik| s_k: the row factor s_i cancels, so only columns are scaled (the
    diagonal is 1 up to rounding instead of exactly).  A dimension without spread falls back to
    the reference function (its row is then e_i)."""
    m = xt @ weights
    np.subtract(xt, m[:, None], out=d)
    np.multiply(d, weights, out=dw)
    cov = dw @ d.T
    var = cov.diagonal()
    if not var.min() > 0.0:
        return correlation_transition(xt.T, weights, "rownorm")
    cov *= 1.0 / np.sqrt(var)
    return cov / np.abs(cov).sum(axis=1, keepdims=True)


def systematic_counts_resample(weights: np.ndarray, u0: float, arange: np.ndarray) -> np.ndarray:
    """Systematic resampling (``resample(..., "systematic")`` with the uniform ``u0``) by counts:
    particle i is kept ceil(N c_i - u0) - ceil(N c_{i-1} - u0) times (c: the cumulative weights),
    which is where the N points (u0 + j) / N fall; ``np.repeat`` instead of a binary search per
    point (the same ancestors up to rounding at the cell edges).  ``arange``: np.arange(N)."""
    n = weights.size
    c = np.cumsum(weights)
    c *= n
    c -= u0
    k = np.ceil(c).astype(np.intp)
    k[-1] = n
    counts = np.empty(n, np.intp)
    counts[0] = k[0]
    np.subtract(k[1:], k[:-1], out=counts[1:])
    return np.repeat(arange, counts)


def correlation_transition(particles: np.ndarray, weights: np.ndarray, stabiliser: str = "rownorm") -> np.ndarray:
    """Theta(k-1) of eq. 12 (Appendix B): the cloud's correlation matrix, made non-expanding.

    A raw correlation matrix has eigenvalues up to P, so chi(k) = Theta chi(k-1) would amplify the
    errors along strongly correlated directions every step.  ``rownorm`` divides each row by its sum
    of absolute values (so ||Theta||_inf = 1: each new error is a weighted average of the old ones,
    the fusion the paper describes); ``spectral`` scales the matrix to spectral radius 1;
    ``raw`` is the literal matrix; ``identity`` switches the fusion off (a random-walk filter).
    """
    p = particles.shape[1]
    if stabiliser == "identity":
        return np.eye(p)
    corr = weighted_correlation(particles, weights)
    if stabiliser == "raw":
        return corr
    if stabiliser == "rownorm":
        return corr / np.abs(corr).sum(axis=1, keepdims=True)
    if stabiliser == "spectral":
        radius = float(np.max(np.abs(np.linalg.eigvalsh(corr))))
        return corr / max(radius, 1.0)
    raise ValueError(f"unknown stabiliser {stabiliser!r} (known: {', '.join(STABILISERS)})")


def propagate(particles: np.ndarray, transition: np.ndarray, noise_std: np.ndarray, rng=None,
              noise: np.ndarray | None = None) -> np.ndarray:
    """chi(k) = Theta chi(k-1) + beta, beta ~ N(0, diag(noise_std^2))  (eq. 12).

    ``noise``: standard normal draws of the particles' shape, if already drawn (a strategy draws
    them ahead of time: one large draw is much cheaper than many small ones).  The result is a
    Fortran-ordered (N, P) array (its transpose is contiguous: the fast layout of this module)."""
    if noise is None:
        noise = rng.standard_normal(particles.shape)
    out = transition @ particles.T
    out += noise.T * noise_std[:, None]
    return out.T


def curve_at(particles: np.ndarray, base_theta: np.ndarray, creep_speed_kmh: float) -> np.ndarray:
    """M_cor(v_s) per particle (N,) at one creep speed: the hot path's model evaluation."""
    n = (particles.shape[1] - 1) // 2
    th = particles.T + base_theta[:, None]
    with np.errstate(over="ignore", invalid="ignore"):
        e = np.exp(th[1 + n:] * creep_speed_kmh)
        out = th[1] * e[0]
        for i in range(1, n):
            out += th[1 + i] * e[i]
        out += th[0]
    return out


def log_likelihood(particles: np.ndarray, base_theta: np.ndarray, creep_speed_kmh, mu_samples,
                   noise_std: float) -> np.ndarray:
    """Sum over the given samples of log N(mu^ ; M_cor(v_s), G), per particle (N,); -inf where the
    corrected curve is not finite."""
    if np.ndim(creep_speed_kmh) == 0:
        resid = float(mu_samples) - curve_at(particles, base_theta, float(creep_speed_kmh))
        ll = resid * resid * (-0.5 / noise_std ** 2)
        if np.isfinite(ll.sum()):
            return ll
    else:
        v = np.asarray(creep_speed_kmh, float)
        y = np.asarray(mu_samples, float)
        resid = y - mu_model(v, base_theta + particles)          # (N, S)
        ll = -0.5 * np.sum(resid * resid, axis=1) / noise_std ** 2
    ll[~np.isfinite(ll)] = -np.inf
    return ll


def normalise(log_weights: np.ndarray) -> np.ndarray:
    """Normalised weights from log weights; all-degenerate (every entry -inf or NaN) -> uniform."""
    top = log_weights.max()
    if np.isfinite(top):              # no NaN (max propagates NaN) and at least one finite entry
        w = np.exp(log_weights - top)
        return w / w.sum()
    lw = np.where(np.isnan(log_weights), -np.inf, log_weights)
    top = np.max(lw)
    if not np.isfinite(top):
        return np.full(lw.shape, 1.0 / lw.size)
    w = np.exp(lw - top)
    return w / w.sum()


def ess(weights: np.ndarray) -> float:
    """Effective sample size 1 / sum(w^2) of normalised weights."""
    return float(1.0 / np.dot(weights, weights))


def resample(weights: np.ndarray, rng, scheme: str = "systematic") -> np.ndarray:
    """Ancestor indices (N,) drawn from ``weights`` (normalised)."""
    n = weights.size
    cdf = np.cumsum(weights)
    cdf[-1] = 1.0
    if scheme == "systematic":
        u = (rng.random() + np.arange(n)) / n
    elif scheme == "stratified":
        u = (rng.random(n) + np.arange(n)) / n
    elif scheme == "multinomial":
        u = np.sort(rng.random(n))
    else:
        raise ValueError(f"unknown resampling scheme {scheme!r} (known: {', '.join(RESAMPLERS)})")
    return np.minimum(np.searchsorted(cdf, u, side="right"), n - 1)


def project_to_box(particles: np.ndarray, lo: np.ndarray, hi: np.ndarray, base_theta: np.ndarray,
                   creep_speed_kmh: float, mu_sample: float, prior_std: np.ndarray, noise_std: float,
                   method: str = "map", iterations: int = 2) -> np.ndarray:
    """Move the edge particles (outside [lo, hi]) into the box (eq. 24); inside ones are untouched.

    ``map``: minimise 0.5 |(chi~ - chi_out)/B|^2 + 0.5 (Z - M_cor(v_s; chi~))^2 / G over the box by
    projected Gauss-Newton steps started from the clipped particle (the measurement is one scalar,
    so each step is a rank-one, Kalman-like update, vectorised over the edge particles); every
    iterate is clipped, so the result is always inside.  ``clip``: the Euclidean projection.
    A non-finite coordinate is replaced by the point of the box nearest to zero first.
    """
    lo_c, hi_c = np.asarray(lo, float)[:, None], np.asarray(hi, float)[:, None]
    xt = particles.T                                   # (P, N): contiguous rows for an F-ordered cloud
    with np.errstate(invalid="ignore"):
        if np.all(xt.min(axis=1) >= lo) and np.all(xt.max(axis=1) <= hi):
            return particles                           # all finite and inside: nothing to do (the common case)
    finite = np.isfinite(xt)
    if not finite.all():
        xt = np.where(finite, xt, np.clip(0.0, lo_c, hi_c))
    edge = ((xt < lo_c) | (xt > hi_c)).any(axis=0)
    out = np.array(xt, order="C", copy=True)
    if not edge.any():
        return out.T
    raw = xt[:, edge]                                  # (P, m)
    z = np.clip(raw, lo_c, hi_c)
    if method == "map" and np.isfinite(mu_sample) and np.isfinite(creep_speed_kmh):
        p_var = (np.asarray(prior_std, float) ** 2)[:, None]
        g_var = noise_std ** 2
        n = (particles.shape[1] - 1) // 2
        v = float(creep_speed_kmh)
        base = np.asarray(base_theta, float)[:, None]
        jac = np.empty_like(z)
        jac[0] = 1.0
        for _ in range(iterations):
            th = base + z
            with np.errstate(over="ignore", invalid="ignore"):
                e = np.exp(th[1 + n:] * v)
                jac[1:1 + n] = e
                jac[1 + n:] = th[1:1 + n] * e * v
                r = mu_sample - th[0] - np.sum(th[1:1 + n] * e, axis=0)
                # linearise M about z and minimise over delta = chi~ - z (prior centred at raw):
                # (P^-1 + J^T J / G) delta = -P^-1 (z - raw) + J^T r / G, solved by Sherman-Morrison.
                # Coordinates on a bound that the step would push outwards are frozen (active set:
                # their variance is set to 0), so the clipped step still fits the measurement.
                pull = raw - z
                pv = np.broadcast_to(p_var, z.shape)
                for _ in range(2):
                    pj = pv * jac
                    pg = pull * (pv > 0) + pj * (r / g_var)
                    delta = pg - pj * (np.sum(jac * pg, axis=0) / (g_var + np.sum(jac * pj, axis=0)))
                    pv = np.where(((z <= lo_c) & (delta < 0)) | ((z >= hi_c) & (delta > 0)), 0.0, pv)
                step = np.clip(z + delta, lo_c, hi_c)
            z = np.where(np.isfinite(step), step, z)
    elif method not in PROJECTORS:
        raise ValueError(f"unknown projection {method!r} (known: {', '.join(PROJECTORS)})")
    out[:, edge] = z
    return out.T


def weighted_quantiles(x: np.ndarray, w: np.ndarray, qs) -> np.ndarray:
    """Quantiles ``qs`` of the weighted sample (x, w), by the inverse of the weighted empirical
    distribution function (the smallest x whose cumulative weight reaches q)."""
    order = np.argsort(x)
    cdf = np.cumsum(w[order])
    idx = np.searchsorted(cdf, np.asarray(qs, float) * cdf[-1], side="left")
    return x[order[np.minimum(idx, x.size - 1)]]


def weighted_interval(x: np.ndarray, w: np.ndarray, level: float) -> tuple[float, float]:
    """The central interval at ``level`` of the weighted sample (x, w), NaN entries of x dropped
    ((NaN, NaN) when nothing is left)."""
    ok = np.isfinite(x)
    if not ok.any():
        return (float("nan"), float("nan"))
    lo, hi = weighted_quantiles(x[ok], w[ok], (0.5 * (1.0 - level), 0.5 * (1.0 + level)))
    return float(lo), float(hi)
