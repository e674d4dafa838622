"""Compiled kernels of the particle filter's step (numba), the same operations as the numpy
pieces of ``identifier/pf.py`` up to rounding.

Why compiled: at N = 1000 particles a numpy call costs a few microseconds of overhead whatever
its arithmetic, and a filter step in numpy needs about 35 of them (~65 us measured); the TCU has
one 1 ms sampling period per sample and the issue asks for p99 <= 5 % of it.  Each kernel below
replaces a group of numpy calls by one pass over the cloud; the filter step allocates nothing.

The numpy pieces stay the reference (strategies run them with the option ``compiled = False``,
and tests/test_kernels.py checks the kernels against them).  Results agree to rounding, not to
the bit: the kernels add in a different order and use their own vectorised ``exp`` (``vexp``).

``AVAILABLE`` is False when numba cannot be imported; the strategies then run the numpy pieces.
Compiled code is cached beside this file (``cache=True``), so only the first use on a machine
pays the compilation (a few seconds); ``warm_up()`` does it ahead of time.
"""
from __future__ import annotations

import math

import numpy as np

try:
    from numba import njit
    AVAILABLE = True
except ImportError:           # the numpy pieces run instead (identifier/pf.py)
    AVAILABLE = False

    def njit(*args, **kwargs):
        def wrap(f):
            return f
        return wrap(args[0]) if args and callable(args[0]) else wrap

# Reductions over particles may be reassociated (so they vectorise); no other fast-math licence:
# NaN and inf keep their IEEE meaning, which the filter's fallbacks rely on.  ``vexp`` gets none
# at all: its range reduction depends on the order of its operations.
_JIT = dict(cache=True, nogil=True, fastmath={"reassoc"}, error_model="numpy")
_JIT_EXACT = dict(cache=True, nogil=True, error_model="numpy")


# exp by Cody-Waite range reduction x = k ln2 + r, |r| <= ln2 / 2, a degree-13 Taylor polynomial
# for e^r (truncation error < 1e-17 relative) and 2^k built in the exponent bits.  The C library's
# exp is a call per element (~7 ns here); this is plain arithmetic the compiler vectorises
# (~1.5 ns).  Agrees with numpy.exp to a few ulp on [-708, 709] (tests/test_kernels.py); below
# -708 it returns 0 where the library returns values under 3e-308 (a weight or a curve term that
# small is zero to the filter), above 709 inf, NaN for NaN.
_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01     # fdlibm's split of ln 2: k * _LN2_HI is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
_INV_FACT = tuple(1.0 / math.factorial(i) for i in range(14))
_BITS_ZERO, _BITS_INF, _BITS_NAN = 0, 0x7FF0000000000000, 0x7FF8000000000000


@njit(**_JIT_EXACT)
def vexp(a, bits):
    """a <- exp(a) in place (float64 (M,)); ``bits``: int64 scratch of at least M."""
    m = a.size
    c = _INV_FACT
    for j in range(m):
        x = a[j]
        xc = x if x > -708.0 else -708.0          # NaN lands here too: its bits are set below
        xc = xc if xc < 709.0 else 709.0
        k = math.floor(xc * _LOG2E + 0.5)
        r = (xc - k * _LN2_HI) - k * _LN2_LO
        p = c[13]
        for i in range(12, -1, -1):           # Horner; a constant trip count, unrolled by the compiler
            p = p * r + c[i]
        a[j] = p
        b = (np.int64(k) + 1023) << 52
        b = _BITS_ZERO if x < -708.0 else b
        b = _BITS_INF if x > 709.0 else b
        b = _BITS_NAN if x != x else b
        bits[j] = b
    scale = bits[:m].view(np.float64)
    for j in range(m):
        a[j] *= scale[j]
    return a


@njit(**_JIT)
def rownorm_propagate(xt, weights, noise, out, d):
    """chi(k) = Theta chi(k-1) + beta with Theta the row-normalised weighted correlation of the
    cloud (``pf.rownorm_transition`` then ``pf.propagate``).  ``xt``: the (P, N) cloud; ``noise``:
    beta, (P, N), already scaled; ``out``: (P, N) result; ``d``: (P, N) scratch.  Returns False,
    leaving ``out`` unwritten, when a dimension has no spread (the caller's reference path handles
    it) or the transition is not finite."""
    p, n = xt.shape
    mean = np.zeros(p)
    for i in range(p):
        s = 0.0
        for j in range(n):
            s += xt[i, j] * weights[j]
        mean[i] = s
    for i in range(p):
        for j in range(n):
            d[i, j] = xt[i, j] - mean[i]
    cov = np.empty((p, p))
    for i in range(p):
        for k in range(i + 1):
            s = 0.0
            for j in range(n):
                s += d[i, j] * weights[j] * d[k, j]
            cov[i, k] = s
            cov[k, i] = s
    inv_sd = np.empty(p)
    for i in range(p):
        if not cov[i, i] > 0.0:
            return False
        inv_sd[i] = 1.0 / math.sqrt(cov[i, i])
    theta = np.empty((p, p))
    for i in range(p):
        row = 0.0
        for k in range(p):
            theta[i, k] = cov[i, k] * inv_sd[k]
            row += abs(theta[i, k])
        if not (row > 0.0 and math.isfinite(row)):
            return False
        for k in range(p):
            theta[i, k] /= row
    for i in range(p):
        for j in range(n):
            out[i, j] = noise[i, j]
        for k in range(p):
            t = theta[i, k]
            for j in range(n):
                out[i, j] += t * xt[k, j]
    return True


@njit(**_JIT)
def log_likelihood(xt, base, creep_speed_kmh, mu_hat, scale, out, tmp, bits):
    """out_j = scale (mu^ - M_cor(v_s; chi_j))^2 with scale = -1 / (2 G): ``pf.log_likelihood``
    at one sample.  Non-finite entries become -inf.  ``tmp``: (n, N) float scratch, ``bits``:
    (N,) int64 scratch.  Returns True when all entries were finite."""
    p, n = xt.shape
    terms = (p - 1) // 2
    for t in range(terms):
        row = tmp[t]
        b = base[1 + terms + t]
        for j in range(n):
            row[j] = (xt[1 + terms + t, j] + b) * creep_speed_kmh
        vexp(row, bits)
    finite = True
    for j in range(n):
        m = (xt[1, j] + base[1]) * tmp[0, j]
        for t in range(1, terms):
            m += (xt[1 + t, j] + base[1 + t]) * tmp[t, j]
        m += xt[0, j] + base[0]
        r = mu_hat - m
        ll = r * r * scale
        if not math.isfinite(ll):
            ll = -math.inf
            finite = False
        out[j] = ll
    return finite


@njit(**_JIT)
def reweigh(log_lik, weights_prev, weights_out, bits):
    """w = w_prev exp(ll - max ll) / sum (``pf.normalise`` of log w_prev + ll when that is finite);
    returns the effective sample size 1 / sum w^2, or -1.0 (``weights_out`` then undefined) when
    the product underflows or is not finite: the caller then normalises in logarithms."""
    n = log_lik.size
    top = -math.inf
    for j in range(n):
        x = log_lik[j]
        if x != x:
            return -1.0
        if x > top:
            top = x
    if not math.isfinite(top):
        return -1.0
    for j in range(n):
        weights_out[j] = log_lik[j] - top
    vexp(weights_out, bits)
    total = 0.0
    for j in range(n):
        w = weights_out[j] * weights_prev[j]
        weights_out[j] = w
        total += w
    if not (total > 0.0 and math.isfinite(total)):
        return -1.0
    ss = 0.0
    for j in range(n):
        w = weights_out[j] / total
        weights_out[j] = w
        ss += w * w
    return 1.0 / ss


@njit(**_JIT)
def filter_step(xt, weights, noise, out, d, base, creep_speed_kmh, mu_hat, scale, lo, hi, use_box, log_lik,
                weights_out, tmp, bits):
    """One whole filter step: ``rownorm_propagate`` into ``out``, clip into the box [lo, hi] (the
    proposed strategy's "clip" projection; ``use_box``), ``log_likelihood``, ``reweigh``.
    Returns the effective sample size, or a code for the caller's reference path to take over:
    -1.0 no transition (nothing written), -2.0 the moved cloud in ``out`` is not finite (not yet
    clipped or weighed), -3.0 the weights underflowed (``out`` moved and clipped, ``log_lik`` set)."""
    if not rownorm_propagate(xt, weights, noise, out, d):
        return -1.0
    p, n = out.shape
    total = 0.0
    for i in range(p):
        for j in range(n):
            total += out[i, j]
    if not math.isfinite(total):
        return -2.0
    if use_box:
        for i in range(p):
            a, b = lo[i], hi[i]
            for j in range(n):
                out[i, j] = min(max(out[i, j], a), b)
    log_likelihood(out, base, creep_speed_kmh, mu_hat, scale, log_lik, tmp, bits)
    ess = reweigh(log_lik, weights, weights_out, bits)
    return -3.0 if ess < 0.0 else ess


@njit(**_JIT)
def systematic_resample(weights, u0, idx):
    """Ancestor indices of systematic resampling with the uniform ``u0``, by counts
    (``pf.systematic_counts_resample``): particle i is kept ceil(N c_i - u0) - ceil(N c_{i-1} - u0)
    times, c the cumulative weights."""
    n = weights.size
    c = 0.0
    filled = 0
    for i in range(n):
        c += weights[i]
        k = n if i == n - 1 else int(math.ceil(c * n - u0))
        k = min(max(k, filled), n)
        for q in range(filled, k):
            idx[q] = i
        filled = k
    return idx


@njit(**_JIT)
def take_columns(xt, idx, out):
    """out[:, q] = xt[:, idx[q]]: the resampled cloud, into a preallocated buffer."""
    p = xt.shape[0]
    for i in range(p):
        for q in range(idx.size):
            out[i, q] = xt[i, idx[q]]


@njit(**_JIT)
def _solve(a, b, x):
    """x = a^-1 b for a small dense system by Gaussian elimination with partial pivoting (LAPACK
    gesv's algorithm, as numpy.linalg.solve); ``a`` and ``b`` are overwritten.  False if singular."""
    k = b.size
    for c in range(k):
        piv, big = c, abs(a[c, c])
        for r in range(c + 1, k):
            if abs(a[r, c]) > big:
                piv, big = r, abs(a[r, c])
        if big == 0.0 or big != big:
            return False
        if piv != c:
            for q in range(k):
                a[c, q], a[piv, q] = a[piv, q], a[c, q]
            b[c], b[piv] = b[piv], b[c]
        for r in range(c + 1, k):
            f = a[r, c] / a[c, c]
            if f != 0.0:
                for q in range(c, k):
                    a[r, q] -= f * a[c, q]
                b[r] -= f * b[c]
    for c in range(k - 1, -1, -1):
        s = b[c]
        for q in range(c + 1, k):
            s -= a[c, q] * x[q]
        x[c] = s / a[c, c]
    return True


@njit(**_JIT)
def _solve_held(a, b, held, x):
    """Solve a x = b on the coordinates not ``held`` (held ones: x = 0); False if singular."""
    k = b.size
    idx = np.empty(k, np.intp)
    m = 0
    for i in range(k):
        x[i] = 0.0
        if not held[i]:
            idx[m] = i
            m += 1
    if m == 0:
        return True
    aa = np.empty((m, m))
    bb = np.empty(m)
    for r in range(m):
        bb[r] = b[idx[r]]
        for c in range(m):
            aa[r, c] = a[idx[r], idx[c]]
    xx = np.empty(m)
    if not _solve(aa, bb, xx):
        return False
    for r in range(m):
        x[idx[r]] = xx[r]
    return True


@njit(**_JIT)
def _residuals(x, v, target, transform, r, jac):
    """r = M(v; x) - target and its Jacobian (S, P); with a (S, S) ``transform`` K (observer-aware
    model) r = K M - target, J = K J.  ``nlls._polish_fun``.  Returns r.r (inf if not finite)."""
    s_count = v.size
    terms = (x.size - 1) // 2
    m = np.empty(s_count)
    jm = np.empty((s_count, x.size))
    for s in range(s_count):
        jm[s, 0] = 1.0
        acc = 0.0
        for t in range(terms):
            e = math.exp(v[s] * x[1 + terms + t])
            jm[s, 1 + t] = e
            jm[s, 1 + terms + t] = e * x[1 + t] * v[s]
            acc += e * x[1 + t]
        m[s] = acc + x[0]
    if transform.shape[0] == 0:
        for s in range(s_count):
            r[s] = m[s] - target[s]
            for q in range(x.size):
                jac[s, q] = jm[s, q]
    else:
        for s in range(s_count):
            acc = 0.0
            for u in range(s_count):
                acc += transform[s, u] * m[u]
            r[s] = acc - target[s]
            for q in range(x.size):
                acc = 0.0
                for u in range(s_count):
                    acc += transform[s, u] * jm[u, q]
                jac[s, q] = acc
    cost = 0.0
    for s in range(s_count):
        cost += r[s] * r[s]
    return cost if math.isfinite(cost) else math.inf


@njit(**_JIT)
def bounded_lm(x0, lo, hi, v, target, transform, iterations, rtol):
    """``nlls.BoundedLm`` run to the end on the curve model: projected Levenberg-Marquardt with
    an active set (coordinates on a bound that the gradient pushes out are held), step clipped
    into [lo, hi], kept only if the cost falls (lambda / 3, else lambda * 4)."""
    p = x0.size
    s_count = v.size
    x = np.minimum(np.maximum(x0, lo), hi)
    if iterations <= 0:
        return x
    r = np.empty(s_count)
    jac = np.empty((s_count, p))
    cost = _residuals(x, v, target, transform, r, jac)
    if not math.isfinite(cost):
        return x
    rn = np.empty(s_count)
    jn = np.empty((s_count, p))
    g = np.empty(p)
    a = np.empty((p, p))
    rhs = np.empty(p)
    step = np.empty(p)
    held = np.empty(p, np.bool_)
    xn = np.empty(p)
    lam = 1e-3
    left = iterations
    while True:
        left -= 1
        for i in range(p):
            acc = 0.0
            for s in range(s_count):
                acc += jac[s, i] * r[s]
            g[i] = acc
            for k in range(p):
                acc = 0.0
                for s in range(s_count):
                    acc += jac[s, i] * jac[s, k]
                a[i, k] = acc
        for i in range(p):
            d = a[i, i]
            a[i, i] = d + lam * (d if d > 0 else 1e-12)
            held[i] = (x[i] <= lo[i] and g[i] > 0) or (x[i] >= hi[i] and g[i] < 0)
            rhs[i] = -g[i]
        if not _solve_held(a, rhs, held, step):
            lam *= 4.0
            if left <= 0:
                break
            continue
        for i in range(p):
            xn[i] = min(max(x[i] + step[i], lo[i]), hi[i])
        cn = _residuals(xn, v, target, transform, rn, jn)
        done = False
        if cn < cost:
            done = cost - cn <= rtol * cost
            x[:] = xn
            r[:] = rn
            jac[:, :] = jn
            cost = cn
            lam = max(lam / 3.0, 1e-9)
        else:
            lam *= 4.0
            done = lam > 1e8
        if done or left <= 0:
            break
    return x


@njit(**_JIT)
def grid_best(a, b, tt, taus, lo, hi):
    """``nlls._grid_best`` on a lattice built by ``nlls.GridAccumulator``: per tau lattice point g
    the linear lambdas from the normal equations a_g lam = b_g (with a 1e-12 trace ridge; one
    active-set pass for the lambda bounds), cost |t|^2 - 2 lam.b + lam.A lam; the best point's
    (lambda, tau)."""
    count, k, _ = a.shape
    n = taus.shape[1]
    best_cost, best = math.inf, 0
    best_lam = np.zeros(k)
    ar = np.empty((k, k))
    rhs = np.empty(k)
    lam = np.empty(k)
    held = np.empty(k, np.bool_)
    for g in range(count):
        trace = 0.0
        for i in range(k):
            trace += a[g, i, i]
        for i in range(k):
            for q in range(k):
                ar[i, q] = a[g, i, q]
            ar[i, i] += 1e-12 * trace
            rhs[i] = b[g, i]
        if not _solve(ar, rhs, lam):
            continue
        out = False
        for i in range(k):
            held[i] = lam[i] < lo[i] or lam[i] > hi[i]
            out = out or held[i]
        if out:
            fixed = np.minimum(np.maximum(lam, lo[:k]), hi[:k])
            for i in range(k):
                acc = b[g, i]
                for q in range(k):
                    if held[q]:
                        acc -= a[g, i, q] * fixed[q]
                rhs[i] = acc
                for q in range(k):
                    ar[i, q] = a[g, i, q]
                ar[i, i] += 1e-12 * trace
            if not _solve_held(ar, rhs, held, lam):
                continue
            for i in range(k):
                lam[i] = fixed[i] if held[i] else min(max(lam[i], lo[i]), hi[i])
        cost = tt
        for i in range(k):
            acc = -2.0 * b[g, i]
            for q in range(k):
                acc += a[g, i, q] * lam[q]
            cost += lam[i] * acc
        if math.isfinite(cost) and cost < best_cost:
            best_cost, best = cost, g
            best_lam[:] = lam
    out_x = np.empty(k + n)
    out_x[:k] = best_lam
    out_x[k:] = taus[best]
    return out_x


def warm_up() -> None:
    """Compile (or load from the cache) every kernel now, e.g. before the fault, not on the first sample."""
    if not AVAILABLE:
        return
    xt = np.zeros((5, 4))
    xt[:, 1] = 1e-3
    w = np.full(4, 0.25)
    rownorm_propagate(xt, w, np.zeros((5, 4)), np.empty((5, 4)), np.empty((5, 4)))
    ll, tmp, bits = np.empty(4), np.empty((2, 4)), np.empty(4, np.int64)
    log_likelihood(xt, np.zeros(5), 1.0, 0.1, -0.5, ll, tmp, bits)
    reweigh(ll, w, np.empty(4), bits)
    filter_step(xt, w, np.zeros((5, 4)), np.empty((5, 4)), np.empty((5, 4)), np.zeros(5), 1.0, 0.1, -0.5,
                np.zeros(5), np.ones(5), True, ll, np.empty(4), tmp, bits)
    vexp(np.zeros(4), bits)
    systematic_resample(w, 0.5, np.empty(4, np.intp))
    take_columns(xt, np.zeros(4, np.intp), np.empty((5, 4)))
    v = np.linspace(0.5, 1.0, 6)
    x = np.array([0.0, 0.1, -0.1, -0.5, -1.0])
    lo, hi = x - 0.1, x + 0.1
    bounded_lm(x, lo, hi, v, np.full(6, 0.1), np.zeros((0, 0)), 2, 1e-10)
    bounded_lm(x, lo, hi, v, np.full(6, 0.1), np.eye(6), 2, 1e-10)
    grid_best(np.tile(np.eye(3), (4, 1, 1)), np.ones((4, 3)), 1.0, np.full((4, 2), -0.5), lo, hi)
