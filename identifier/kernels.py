"""Compiled kernels of the particle filter's step (numba), the same operations as the numpy
pieces of ``identifier/pf.py`` up to rounding.

Why compiled: at N = 1000 particles a numpy call costs a few microseconds of overhead whatever
its arithmetic, and a filter step in numpy needs about 35 of them; the TCU has one sampling period
per sample and the issue asks for a p99 of at most 5 % of it.  Each kernel below replaces a group of
numpy calls by a few passes over the cloud; the filter step allocates one (P + 1, P) array and
nothing per particle.  What each kernel costs, and what it replaced: docs/design/identifier.md.

How the step gets there: the five-parameter model (two exponential terms, the strategies' only
size) has its own pieces (``_moments5``, ``_move_weigh5``) that keep every per-particle quantity in
registers: one pass for the means, one for the covariance from values centred on the fly (the
centred cloud is never stored), and one that moves a particle, checks it, clips it and weighs it
(curve, residual, log-likelihood) before the next; then short passes over the N log-likelihoods
for their maximum, the weights and their normalisation.  Other sizes go through the generic
kernels, a pass per operation.

The numpy pieces stay the reference (strategies run them with the option ``compiled = False``,
and tests/test_kernels.py checks the kernels against them).  Results agree to rounding, not to
the bit: the kernels add in a different order and use their own vectorised ``exp`` (``_exp``).

``AVAILABLE`` is False when numba cannot be imported; the strategies then run the numpy pieces.
Compiled code is cached beside this file (``cache=True``), so only the first use on a machine
pays the compilation (~15 s on a 2-core machine); ``warm_up()`` does it ahead of time.
"""
from __future__ import annotations

import math

import numpy as np

try:
    from llvmlite import ir as _ir
    from numba import njit
    from numba.core import types as _types
    from numba.extending import intrinsic as _intrinsic
    AVAILABLE = True
except ImportError:           # the numpy pieces run instead (identifier/pf.py)
    AVAILABLE = False
    _intrinsic = None

    def njit(*args, **kwargs):
        def wrap(f):
            return f
        return wrap(args[0]) if args and callable(args[0]) else wrap

# Reductions over particles may be reassociated (so they vectorise); no other fast-math licence:
# NaN and inf keep their IEEE meaning, which the filter's fallbacks rely on.  ``_exp`` gets only
# "contract" (its multiply-adds fused: fewer operations, rounding no worse) and no reassociation:
# its range reduction depends on the order of its operations.  Resampling gets no licence at all:
# its cumulative sum must be numpy's, term by term, to pick the reference's ancestors.
_JIT = dict(cache=True, nogil=True, fastmath={"reassoc"}, error_model="numpy")
_JIT_EXACT = dict(cache=True, nogil=True, error_model="numpy")
_JIT_EXP = dict(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")


# Bit casts and an IEEE maxNum, which numba's Python-level code cannot express: built as LLVM
# instructions so they vectorise with the loops around them.
if AVAILABLE:
    @_intrinsic
    def _as_float(typingctx, b):
        """The float64 whose bits are the int64 ``b``."""
        if b != _types.int64:
            return None
        return _types.float64(_types.int64), lambda context, builder, sig, args: builder.bitcast(
            args[0], _ir.DoubleType())

    @_intrinsic
    def _as_int(typingctx, x):
        """The int64 holding the bits of the float64 ``x``."""
        if x != _types.float64:
            return None
        return _types.int64(_types.float64), lambda context, builder, sig, args: builder.bitcast(
            args[0], _ir.IntType(64))

    @_intrinsic
    def _maxnum(typingctx, a, b):
        """max(a, b) for float64, the other operand if one is NaN (llvm.maxnum): unlike a compare
        and select, a reduction by it vectorises without a no-NaN licence.  Only used where no
        NaN can occur (or is caught separately)."""
        if a != _types.float64 or b != _types.float64:
            return None

        def codegen(context, builder, sig, args):
            d = _ir.DoubleType()
            fn = builder.module.declare_intrinsic("llvm.maxnum", [d], _ir.FunctionType(d, [d, d]))
            return builder.call(fn, args)
        return _types.float64(_types.float64, _types.float64), codegen
else:                          # plain Python (the kernels are then unused, but still correct)
    def _as_float(b):
        return float(np.uint64(b & 0xFFFF_FFFF_FFFF_FFFF).view(np.float64))

    def _as_int(x):
        return int(np.float64(x).view(np.int64))

    def _maxnum(a, b):
        return b if a != a or b > a else a


# exp by Cody-Waite range reduction x = k ln2 + r, |r| <= ln2 / 2, a degree-13 Taylor polynomial
# for e^r (truncation error < 1e-17 relative) by Horner's rule in fused multiply-adds, and 2^k
# built in the exponent bits.  The C library's exp is a call per element; this is plain arithmetic
# the compiler vectorises and inlines into the loops that call it, bound by its 16 multiply-adds
# (degree 13 is what 1 ulp needs: a degree-11 minimax fit would be faster but add ~0.15 ulp;
# costs in docs/design/identifier.md).  Agrees with numpy.exp to 1 ulp on [-708, 709]
# (tests/test_kernels.py); below -708 it returns 0 where the library returns values under 3e-308
# (a weight or a curve term that small is zero to the filter), above 709 inf, NaN for NaN.
_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01     # fdlibm's split of ln 2: k * _LN2_HI is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
_ROUND = 6755399441055744.0              # 1.5 * 2^52: t + _ROUND - _ROUND rounds t to an integer (|t| < 2^51)
_C = tuple(1.0 / math.factorial(i) for i in range(14))


@njit(**_JIT_EXP)
def _exp(x):
    """exp(x) for one float64 (see above); branch-free, so it vectorises where it is inlined."""
    xc = -708.0 if x < -708.0 else x          # NaN stays NaN and flows through to the result
    xc = 709.0 if xc > 709.0 else xc
    t = xc * _LOG2E + _ROUND                  # k = round(x / ln 2), held in t's low mantissa bits
    k = t - _ROUND
    r = (xc - k * _LN2_HI) - k * _LN2_LO
    c = _C
    p = c[13]
    for i in range(12, -1, -1):               # a constant trip count: compiled fully unrolled
        p = p * r + c[i]
    y = p * _as_float((_as_int(t) + 1023) << 52)   # 2^k: k + 1023 in the exponent field (t's high bits shift out)
    y = 0.0 if x < -708.0 else y
    return math.inf if x > 709.0 else y


@njit(**_JIT_EXACT)
def vexp(a):
    """a <- exp(a) in place (float64 (M,)) by ``_exp``."""
    for j in range(a.size):
        a[j] = _exp(a[j])
    return a


@njit(**_JIT)
def weighted_mean(xt, weights, out):
    """out[i] = sum_j xt[i, j] w_j: the weighted mean of the (P, N) cloud (``weights @ xt.T``), (P,)."""
    p, n = xt.shape
    for i in range(p):
        x = xt[i]
        s = 0.0
        for j in range(n):
            s += x[j] * weights[j]
        out[i] = s
    return out


@njit(**_JIT)
def _covariance(xt, weights, d, cov):
    """cov (P, P) <- the weighted covariance of the (P, N) cloud; ``d``: (P, N) scratch (the centred
    cloud).  Any P, a pass per row and per pair (``_moments5``: five rows in two passes)."""
    p, n = xt.shape
    for i in range(p):
        x, di = xt[i], d[i]
        s = 0.0
        for j in range(n):
            s += x[j] * weights[j]
        for j in range(n):
            di[j] = x[j] - s
    for i in range(p):
        di = d[i]
        for k in range(i + 1):
            dk = d[k]
            s = 0.0
            for j in range(n):
                s += di[j] * weights[j] * dk[j]
            cov[i, k] = s
            cov[k, i] = s


@njit(**_JIT)
def _moments5(xt, weights, cov):
    """``_covariance`` of a five-row cloud without its scratch: the means in one pass, then the 15
    sums of centred products in one more, every running sum in a register (the centred values are
    made on the fly; storing them would be a third 40 kB pass at N = 1000)."""
    n = xt.shape[1]
    x0, x1, x2, x3, x4 = xt[0], xt[1], xt[2], xt[3], xt[4]
    m0 = m1 = m2 = m3 = m4 = 0.0
    for j in range(n):
        w = weights[j]
        m0 += x0[j] * w
        m1 += x1[j] * w
        m2 += x2[j] * w
        m3 += x3[j] * w
        m4 += x4[j] * w
    s00 = s10 = s11 = s20 = s21 = s22 = s30 = s31 = s32 = s33 = s40 = s41 = s42 = s43 = s44 = 0.0
    for j in range(n):
        w = weights[j]
        d0, d1, d2, d3, d4 = x0[j] - m0, x1[j] - m1, x2[j] - m2, x3[j] - m3, x4[j] - m4
        e0, e1, e2, e3, e4 = d0 * w, d1 * w, d2 * w, d3 * w, d4 * w
        s00 += e0 * d0
        s10 += e1 * d0
        s11 += e1 * d1
        s20 += e2 * d0
        s21 += e2 * d1
        s22 += e2 * d2
        s30 += e3 * d0
        s31 += e3 * d1
        s32 += e3 * d2
        s33 += e3 * d3
        s40 += e4 * d0
        s41 += e4 * d1
        s42 += e4 * d2
        s43 += e4 * d3
        s44 += e4 * d4
    cov[0, 0] = s00
    cov[1, 0] = cov[0, 1] = s10
    cov[1, 1] = s11
    cov[2, 0] = cov[0, 2] = s20
    cov[2, 1] = cov[1, 2] = s21
    cov[2, 2] = s22
    cov[3, 0] = cov[0, 3] = s30
    cov[3, 1] = cov[1, 3] = s31
    cov[3, 2] = cov[2, 3] = s32
    cov[3, 3] = s33
    cov[4, 0] = cov[0, 4] = s40
    cov[4, 1] = cov[1, 4] = s41
    cov[4, 2] = cov[2, 4] = s42
    cov[4, 3] = cov[3, 4] = s43
    cov[4, 4] = s44


@njit(**_JIT)
def weighted_covariance5(xt, weights, cov):
    """cov (5, 5) <- the weighted covariance of a five-row cloud (``_moments5``)."""
    _moments5(xt, weights, cov)
    return cov


@njit(**_JIT_EXACT)
def cholesky_lower(a, out):
    """out <- L, lower triangular with L L^T = a (symmetric positive definite, small: the cloud's
    5 x 5 covariance); at this size numpy.linalg.cholesky's cost is its call overhead."""
    p = a.shape[0]
    out[:, :] = 0.0
    for i in range(p):
        for k in range(i + 1):
            s = a[i, k]
            for m in range(k):
                s -= out[i, m] * out[k, m]
            if i == k:
                out[i, i] = math.sqrt(s) if s > 0.0 else 0.0
            else:
                out[i, k] = s / out[k, k] if out[k, k] > 0.0 else 0.0
    return out


@njit(**_JIT)
def _rownorm(cov, inv_sd):
    """cov (P, P) <- Theta in place: the correlation C_ik s_i s_k (s = 1 / sd) row-normalised, i.e.
    C_ik s_k / sum_k |C_ik s_k| (s_i cancels; ``pf.rownorm_transition``).  ``inv_sd``: (P,) scratch.
    False when a dimension has no spread or a row is not finite (Theta then undefined)."""
    p = cov.shape[0]
    for i in range(p):
        if not cov[i, i] > 0.0:
            return False
        inv_sd[i] = 1.0 / math.sqrt(cov[i, i])
    for i in range(p):
        row = 0.0
        for k in range(p):
            t = cov[i, k] * inv_sd[k]
            cov[i, k] = t
            row += abs(t)
        if not (row > 0.0 and math.isfinite(row)):
            return False
        for k in range(p):
            cov[i, k] /= row
    return True


@njit(**_JIT)
def _transition(xt, weights, d, mat):
    """Theta of the cloud into mat[:P] ((P + 1, P) scratch, its last row for 1 / sd); False if none."""
    p = xt.shape[0]
    theta = mat[:p]
    if p == 5:
        _moments5(xt, weights, theta)
    else:
        _covariance(xt, weights, d, theta)
    return _rownorm(theta, mat[p])


@njit(**_JIT)
def _propagate(xt, theta, noise, out):
    """out = Theta xt + noise, (P, N), a pass per row and term."""
    p, n = xt.shape
    for i in range(p):
        o, b = out[i], noise[i]
        for j in range(n):
            o[j] = b[j]
        for k in range(p):
            t, x = theta[i, k], xt[k]
            for j in range(n):
                o[j] += t * x[j]


@njit(**_JIT)
def _coefficients5(theta):
    """Theta's 25 entries as scalars, row by row, so that a loop over particles keeps them in registers."""
    return (theta[0, 0], theta[0, 1], theta[0, 2], theta[0, 3], theta[0, 4],
            theta[1, 0], theta[1, 1], theta[1, 2], theta[1, 3], theta[1, 4],
            theta[2, 0], theta[2, 1], theta[2, 2], theta[2, 3], theta[2, 4],
            theta[3, 0], theta[3, 1], theta[3, 2], theta[3, 3], theta[3, 4],
            theta[4, 0], theta[4, 1], theta[4, 2], theta[4, 3], theta[4, 4])


@njit(**_JIT)
def _moved5(xt, noise, j, a):
    """Theta x_j + beta_j, particle j of a five-row cloud, as five scalars; ``a``: ``_coefficients5``."""
    y0, y1, y2, y3, y4 = xt[0, j], xt[1, j], xt[2, j], xt[3, j], xt[4, j]
    return (noise[0, j] + a[0] * y0 + a[1] * y1 + a[2] * y2 + a[3] * y3 + a[4] * y4,
            noise[1, j] + a[5] * y0 + a[6] * y1 + a[7] * y2 + a[8] * y3 + a[9] * y4,
            noise[2, j] + a[10] * y0 + a[11] * y1 + a[12] * y2 + a[13] * y3 + a[14] * y4,
            noise[3, j] + a[15] * y0 + a[16] * y1 + a[17] * y2 + a[18] * y3 + a[19] * y4,
            noise[4, j] + a[20] * y0 + a[21] * y1 + a[22] * y2 + a[23] * y3 + a[24] * y4)


@njit(**_JIT)
def _propagate5(xt, theta, noise, out):
    """``_propagate`` of a five-row cloud in one pass, a particle at a time (instead of a pass per row)."""
    a = _coefficients5(theta)
    for j in range(xt.shape[1]):
        out[0, j], out[1, j], out[2, j], out[3, j], out[4, j] = _moved5(xt, noise, j, a)


@njit(**_JIT)
def rownorm_propagate(xt, weights, noise, out, d):
    """chi(k) = Theta chi(k-1) + beta with Theta the row-normalised weighted correlation of the
    cloud (``pf.rownorm_transition`` then ``pf.propagate``).  ``xt``: the (P, N) cloud; ``noise``:
    beta, (P, N), already scaled; ``out``: (P, N) result; ``d``: (P, N) scratch (unused at P = 5).
    Returns False, leaving ``out`` unwritten, when a dimension has no spread (the caller's
    reference path handles it) or the transition is not finite."""
    p = xt.shape[0]
    mat = np.empty((p + 1, p))
    if not _transition(xt, weights, d, mat):
        return False
    if p == 5:
        _propagate5(xt, mat[:p], noise, out)
    else:
        _propagate(xt, mat[:p], noise, out)
    return True


@njit(**_JIT)
def log_likelihood(xt, base, creep_speed_kmh, mu_hat, scale, out, tmp):
    """out_j = scale (mu^ - M_cor(v_s; chi_j))^2 with scale = -1 / (2 G): ``pf.log_likelihood``
    at one sample.  Non-finite entries become -inf.  ``tmp``: (n, N) float scratch (the curve's
    exponentials).  Returns True when all entries were finite.  A pass
    per term; ``_move_weigh5`` does the five-parameter model in the step's own pass."""
    p, n = xt.shape
    terms = (p - 1) // 2
    for t in range(terms):
        e, x, b = tmp[t], xt[1 + terms + t], base[1 + terms + t]
        for j in range(n):
            e[j] = _exp((x[j] + b) * creep_speed_kmh)
    for j in range(n):
        out[j] = 0.0
    for t in range(terms):                    # sum_t lambda_t e_t, in out
        e, x, b = tmp[t], xt[1 + t], base[1 + t]
        for j in range(n):
            out[j] += (x[j] + b) * e[j]
    x, b = xt[0], base[0]
    bad = False
    for j in range(n):
        r = mu_hat - (out[j] + (x[j] + b))
        ll = r * r * scale
        ok = abs(ll) < math.inf               # False for NaN too
        out[j] = ll if ok else -math.inf
        bad |= not ok
    return not bad


@njit(**_JIT)
def _weigh_shifted(log_lik, top, weights_prev, weights_out):
    """weights_out = w_prev exp(ll - top) / sum and its effective sample size 1 / sum w^2, or -1.0
    (``weights_out`` undefined) when the sum underflows or is not finite (a NaN in ``log_lik``
    makes it NaN).  ``top``: max ll, finite."""
    n = log_lik.size
    total = 0.0
    for j in range(n):
        w = _exp(log_lik[j] - top) * weights_prev[j]
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
def _top(log_lik):
    """max_j log_lik_j, NaN entries skipped (-inf if all are NaN or there are none).  A loop of its
    own: the maxNum reduction vectorises alone, not beside other reductions or the step's pass."""
    top = -math.inf
    for j in range(log_lik.size):
        top = _maxnum(top, log_lik[j])
    return top


@njit(**_JIT)
def reweigh(log_lik, weights_prev, weights_out):
    """w = w_prev exp(ll - max ll) / sum (``pf.normalise`` of log w_prev + ll when that is finite);
    returns the effective sample size 1 / sum w^2, or -1.0 (``weights_out`` then undefined) when
    ``log_lik`` holds NaN or no finite maximum, or the product underflows or is not finite: the
    caller then normalises in logarithms."""
    top = _top(log_lik)
    if not math.isfinite(top):
        return -1.0
    return _weigh_shifted(log_lik, top, weights_prev, weights_out)     # a NaN in ll makes its sum NaN: -1.0


@njit(**_JIT)
def _move_weigh5(xt, theta, noise, out, box, lo, hi, base, creep_speed_kmh, mu_hat, scale, log_lik):
    """The five-parameter step's pass over the particles, one at a time with everything in
    registers: out_j = Theta x_j + beta_j, clipped into [lo, hi] when ``box``; log_lik_j as
    ``log_likelihood`` computes it on the clipped particle.  Returns (the sum of the moved values
    before the clip: finite iff they all are, as ``filter_step`` checks; max_j log_lik_j)."""
    n = xt.shape[1]
    a = _coefficients5(theta)
    inf = math.inf
    l0, l1, l2, l3, l4 = (lo[0], lo[1], lo[2], lo[3], lo[4]) if box else (-inf, -inf, -inf, -inf, -inf)
    h0, h1, h2, h3, h4 = (hi[0], hi[1], hi[2], hi[3], hi[4]) if box else (inf, inf, inf, inf, inf)
    c0, c1, c2, c3, c4 = base[0], base[1], base[2], base[3], base[4]
    v = creep_speed_kmh
    total = 0.0
    for j in range(n):
        z0, z1, z2, z3, z4 = _moved5(xt, noise, j, a)
        total += z0 + z1 + z2 + z3 + z4
        z0 = l0 if z0 < l0 else z0
        z0 = h0 if z0 > h0 else z0
        z1 = l1 if z1 < l1 else z1
        z1 = h1 if z1 > h1 else z1
        z2 = l2 if z2 < l2 else z2
        z2 = h2 if z2 > h2 else z2
        z3 = l3 if z3 < l3 else z3
        z3 = h3 if z3 > h3 else z3
        z4 = l4 if z4 < l4 else z4
        z4 = h4 if z4 > h4 else z4
        out[0, j], out[1, j], out[2, j], out[3, j], out[4, j] = z0, z1, z2, z3, z4
        m = (z1 + c1) * _exp((z3 + c3) * v) + (z2 + c2) * _exp((z4 + c4) * v) + (z0 + c0)
        r = mu_hat - m
        ll = r * r * scale
        ll = ll if abs(ll) < inf else -inf    # NaN too: no NaN reaches the maximum
        log_lik[j] = ll
    return total, _top(log_lik)               # a pass of its own: in the loop above it stops the vectorising


@njit(**_JIT)
def filter_step(xt, weights, noise, out, d, base, creep_speed_kmh, mu_hat, scale, lo, hi, use_box, log_lik,
                weights_out, tmp):
    """One whole filter step: ``rownorm_propagate`` into ``out``, clip into the box [lo, hi] (the
    proposed strategy's "clip" projection; ``use_box``), ``log_likelihood``, ``reweigh``.
    Returns the effective sample size, or a code for the caller's reference path to take over:
    -1.0 no transition (nothing written), -2.0 the moved cloud in ``out`` is not finite (not yet
    clipped or weighed), -3.0 the weights underflowed (``out`` moved and clipped, ``log_lik`` set).
    At P = 5: ``_moments5``, then ``_move_weigh5`` (``d`` and ``tmp`` unused); else the
    generic kernels in turn."""
    p, n = xt.shape
    if p != 5:
        if not rownorm_propagate(xt, weights, noise, out, d):
            return -1.0
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
        log_likelihood(out, base, creep_speed_kmh, mu_hat, scale, log_lik, tmp)
        ess = reweigh(log_lik, weights, weights_out)
        return -3.0 if ess < 0.0 else ess
    mat = np.empty((p + 1, p))
    if not _transition(xt, weights, d, mat):
        return -1.0
    theta = mat[:p]
    total, top = _move_weigh5(xt, theta, noise, out, use_box, lo, hi, base, creep_speed_kmh, mu_hat, scale, log_lik)
    if not math.isfinite(total):
        _propagate5(xt, theta, noise, out)   # rare: the caller wants the moved cloud unclipped
        return -2.0
    if not math.isfinite(top):                # every likelihood is 0
        return -3.0
    ess = _weigh_shifted(log_lik, top, weights, weights_out)
    return -3.0 if ess < 0.0 else ess


@njit(**_JIT)
def recentre(xt, shift, lo, hi, use_box):
    """xt[i, j] <- xt[i, j] - shift[i], then clipped into [lo_i, hi_i] when ``use_box``: a correction's
    re-centring of the (P, N) cloud on the new theta and the clip into the new box, in one pass
    (numpy's ``xt -= shift[:, None]``, ``maximum``, ``minimum`` to the bit)."""
    p, n = xt.shape
    for i in range(p):
        x, s, a, b = xt[i], shift[i], lo[i], hi[i]
        if use_box:
            for j in range(n):
                x[j] = min(max(x[j] - s, a), b)
        else:
            for j in range(n):
                x[j] = x[j] - s


# Systematic resampling writes each particle's copies as one run of ancestor indices.  A loop of
# the particle's count mispredicts on almost every particle when the weights are new; instead every particle stores a block of _RUN copies of its index where its run
# starts (no branch on the count), and the next particle's block overwrites the excess.  Only
# counts above _RUN (a weight over _RUN / N: a few particles when the ESS is low) and the last
# _RUN slots, where a block would overrun, take a loop.  What remains is the cumulative sum's
# chain of additions: it must be sequential to be numpy's to the bit.  _RUN = 4 balances fewer
# stores (than 8) against fewer counts above it (than 2); measured: docs/design/identifier.md.
_RUN = 4


@njit(**_JIT_EXACT)
def systematic_resample(weights, u0, idx):
    """Ancestor indices of systematic resampling with the uniform ``u0``, by counts
    (``pf.systematic_counts_resample``): particle i is kept ceil(N c_i - u0) - ceil(N c_{i-1} - u0)
    times, c the cumulative weights (summed in numpy's order, so the counts are the reference's
    to the bit); the last particle takes whatever remains (c_N may round off 1).  ``idx``: (N,) intp."""
    n = weights.size
    c = 0.0
    filled = 0
    for i in range(n):
        c += weights[i]
        k = n if i == n - 1 else int(math.ceil(c * n - u0))
        k = min(max(k, filled), n)
        if filled <= n - _RUN:
            for q in range(_RUN):             # unrolled: _RUN stores, no loop; the excess is the next particles'
                idx[filled + q] = i
            for q in range(filled + _RUN, k):
                idx[q] = i
        else:
            for q in range(filled, k):
                idx[q] = i
        filled = k
    return idx


@njit(**_JIT)
def take_columns(xt, idx, out):
    """out[:, q] = xt[:, idx[q]]: the resampled cloud, into a preallocated buffer.  Five rows: a
    column at a time, each index read (and checked for wraparound) once for the five."""
    p = xt.shape[0]
    if p == 5:
        for q in range(idx.size):
            j = idx[q]
            out[0, q], out[1, q], out[2, q], out[3, q], out[4, q] = xt[0, j], xt[1, j], xt[2, j], xt[3, j], xt[4, j]
        return
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
def grid_add(taus, creep_speed_kmh, target, phi, a, b):
    """One sample into every tau-lattice point's normal equations (``nlls.GridAccumulator.add``
    without a transform): phi_g = (1, exp(tau_g v_s)) into ``phi`` (G, 1 + n), a_g += phi_g phi_g^T
    (``a``: (G, 1 + n, 1 + n)), b_g += phi_g target (``b``: (G, 1 + n))."""
    count, n = taus.shape
    for g in range(count):
        phi[g, 0] = 1.0
        for i in range(n):
            phi[g, 1 + i] = math.exp(taus[g, i] * creep_speed_kmh)
        for i in range(n + 1):
            pi = phi[g, i]
            b[g, i] += pi * target
            for k in range(n + 1):
                a[g, i, k] += pi * phi[g, k]


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


_warmed = False


# -- the bayes strategy (identifier/strategies/bayes.py): its cloud's step, move and intervals ---------
# The same operations as its numpy reference (speed_likelihood.SpeedFilter, prior.phi_from_u /
# theta_from_phi, pf.weighted_quantiles) in branch-free loops around ``_exp``, so they vectorise.
@njit(**_JIT)
def bayes_step(l0, l1, l2, t1, t2, omega, delta, m_prev, log_w, ll_total, weights, creep_speed_kmh, y, torque_nm,
               dt_j, torque_per_mu, inv_2s, gain, gain_delta, out):
    """``SpeedFilter.step`` for every particle's curve M_j(v) = l0 + l1 e^(t1 v) + l2 e^(t2 v) at
    ``creep_speed_kmh`` and its offset ``delta`` (gain ``gain_delta``), log w_j and the particle's
    whole log-likelihood += log L_j, then the normalised weights.  ``out[0]``: the ESS (-1.0
    when the weights are not finite); ``out[1]``: the normalised innovation squared e^2 / S averaged
    with the weights before this step."""
    n = omega.size
    half = 0.5 * torque_per_mu
    nis = 0.0
    for j in range(n):       # (SpeedFilter.step written out here and in bayes_rerun: a shared helper
        #                          returning a tuple stops the loop vectorising)
        m_new = l0[j] + l1[j] * _exp(t1[j] * creep_speed_kmh) + l2[j] * _exp(t2[j] * creep_speed_kmh)
        pred = omega[j] + dt_j * (torque_nm - half * (m_prev[j] + m_new) - torque_per_mu * delta[j])
        e = y - pred
        omega[j] = pred + gain * e
        delta[j] += gain_delta * e
        m_prev[j] = m_new
        log_w[j] -= inv_2s * e * e
        ll_total[j] -= inv_2s * e * e
        nis += weights[j] * e * e
    out[1] = 2.0 * inv_2s * nis
    out[0] = -1.0
    top = _top(log_w)
    if not math.isfinite(top):
        return
    total = 0.0
    for j in range(n):
        w = _exp(log_w[j] - top)
        weights[j] = w
        total += w
    sq = 0.0
    for j in range(n):
        w = weights[j] / total
        weights[j] = w
        sq += w * w
    out[0] = 1.0 / sq


@njit(**_JIT)
def bayes_rerun(l0, l1, l2, t1, t2, creep, y, torque, dt_j, gain, inv_2s, gain_delta, torque_per_mu, ll, omega,
                delta, m_last):
    """Every particle's speed filter over the samples so far, afresh (``SpeedFilter`` from the first
    sample: omega = y[0], delta = 0): its whole log-likelihood, its speed estimate, its offset and M at
    the last sample.  ``dt_j``, ``gain``, ``inv_2s``, ``gain_delta``: the filter's shared constants of
    each step (index k: from sample k - 1 to k), the same for every particle.  Particles are the inner
    loop, so it vectorises."""
    n = l0.size
    half = 0.5 * torque_per_mu
    for j in range(n):
        omega[j] = y[0]
        delta[j] = 0.0
        ll[j] = 0.0
        m_last[j] = l0[j] + l1[j] * _exp(t1[j] * creep[0]) + l2[j] * _exp(t2[j] * creep[0])
    for k in range(1, creep.size):
        v, yk, tq, d, g, s, gd = creep[k], y[k], torque[k - 1], dt_j[k], gain[k], inv_2s[k], gain_delta[k]
        for j in range(n):
            m_new = l0[j] + l1[j] * _exp(t1[j] * v) + l2[j] * _exp(t2[j] * v)
            pred = omega[j] + d * (tq - half * (m_last[j] + m_new) - torque_per_mu * delta[j])
            e = yk - pred
            omega[j] = pred + g * e
            delta[j] += gd * e
            m_last[j] = m_new
            ll[j] -= s * e * e


@njit(**_JIT)
def bayes_move(ut, phit, l0, l1, l2, t1, t2, omega, delta, m_prev, ll, start, stop, chol, normals, uniforms, lo,
               hi, log_scale, creep, y, torque, dt_j, gain, inv_2s, gain_delta, torque_per_mu):
    """One Metropolis step for particles [start, stop) of the cloud, in place (``BayesStrategy._move``):
    proposal u' = u + chol z (z: ``normals``' columns), its curve (``bayes_curves``) and its filter
    over every sample so far (``bayes_rerun``), accepted when uniform < L(u') p(u') / (L(u) p(u)),
    p(u) = prod s (1 - s) with s = sigmoid(u) (each coordinate is the logit of a uniform; the
    numpy reference compares logs instead).  Every loop runs over the particles, so each
    vectorises: a scalar ``_exp`` is bound by its chain of multiply-adds (~15 ns), not its
    throughput (~0.8 ns).  Returns the number accepted."""
    p = ut.shape[0]
    n = stop - start
    prop = np.empty((p, n))
    for i in range(p):
        row = prop[i]
        for q in range(n):
            row[q] = ut[i, start + q]
        for k in range(p):
            c = chol[i, k]
            for q in range(n):
                row[q] += c * normals[k, start + q]
    phip = np.empty((p, n))
    a0, a1, a2, a3, a4 = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    bayes_curves(prop, lo, hi, log_scale, phip, a0, a1, a2, a3, a4)
    llp, omp, dp, mp = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    bayes_rerun(a0, a1, a2, a3, a4, creep, y, torque, dt_j, gain, inv_2s, gain_delta, torque_per_mu, llp, omp, dp, mp)
    ratio = np.empty(n)
    for q in range(n):
        ratio[q] = _exp(llp[q] - ll[start + q])
    for i in range(p):
        for q in range(n):
            e_new = _exp(-abs(prop[i, q]))
            e_old = _exp(-abs(ut[i, start + q]))
            d_new, d_old = 1.0 + e_new, 1.0 + e_old
            ratio[q] *= (e_new * d_old * d_old) / (e_old * d_new * d_new)
    accepted = 0
    for q in range(n):
        j = start + q
        if uniforms[j] < ratio[q]:
            for i in range(p):
                ut[i, j] = prop[i, q]
                phit[i, j] = phip[i, q]
            l0[j], l1[j], l2[j], t1[j], t2[j] = a0[q], a1[q], a2[q], a3[q], a4[q]
            ll[j], omega[j], delta[j], m_prev[j] = llp[q], omp[q], dp[q], mp[q]
            accepted += 1
    return accepted


@njit(**_JIT)
def baseline_stats(buf, count):
    """``bayes.BaselineStats``' two statistics from its ring buffer ``buf`` (rows: step, motor speed,
    train speed; ``count`` readings written, the oldest overwritten): sqrt(mean(d2^2) / 6) of the
    motor speed's second differences d2, and the least-squares line of the train speed in the step,
    (step0, v at step0, slope).  Order matters only for the differences: walked oldest first."""
    size = buf.shape[1]
    n = min(count, size)
    first = count % size if count > size else 0
    sq = 0.0
    for q in range(2, n):
        a, b, c = buf[1, (first + q - 2) % size], buf[1, (first + q - 1) % size], buf[1, (first + q) % size]
        d2 = c - 2.0 * b + a
        sq += d2 * d2
    sigma = math.sqrt(sq / (n - 2) / 6.0) if n >= 8 else math.nan
    k0 = 0.0
    v0 = 0.0
    for q in range(n):
        k0 += buf[0, q]
        v0 += buf[2, q]
    k0 /= n
    v0 /= n
    skk = 0.0
    skv = 0.0
    for q in range(n):
        dk = buf[0, q] - k0
        skk += dk * dk
        skv += dk * (buf[2, q] - v0)
    return sigma, k0, v0, skv / max(skk, 1e-12)


@njit(**_JIT)
def bayes_curves(ut, lo, hi, log_scale, phit, l0, l1, l2, t1, t2):
    """phi = prior.phi_from_u(u) and theta = prior.theta_from_phi(phi) for every particle; ``ut`` and
    ``phit`` are (5, N): a row per coordinate, so every loop runs over contiguous particles."""
    p, n = ut.shape
    for i in range(p):
        span = hi[i] - lo[i]
        row, src = phit[i], ut[i]
        if log_scale[i]:
            for j in range(n):
                row[j] = _exp(lo[i] + span / (1.0 + _exp(-src[j])))
        else:
            for j in range(n):
                row[j] = lo[i] + span / (1.0 + _exp(-src[j]))
    mp, vp, m0, a, r = phit[0], phit[1], phit[2], phit[3], phit[4]
    for j in range(n):
        tau1 = -a[j] / vp[j]
        e_a = _exp(-a[j])
        e_ra = _exp((r[j] - 1.0) * a[j])
        lam1 = (mp[j] - m0[j]) / ((e_a - 1.0) - (e_a - e_ra) / r[j])
        lam2 = -(lam1 / r[j]) * e_ra
        l0[j] = m0[j] - lam1 - lam2
        l1[j] = lam1
        l2[j] = lam2
        t1[j] = tau1
        t2[j] = r[j] * tau1


@njit(**_JIT)
def bayes_mu_at(l0, l1, l2, t1, t2, creep_speed_kmh, out):
    """out_j = M_j(v_s) for every particle's curve."""
    for j in range(out.size):
        out[j] = l0[j] + l1[j] * _exp(t1[j] * creep_speed_kmh) + l2[j] * _exp(t2[j] * creep_speed_kmh)


@njit(**_JIT_EXACT)
def cloud_peaks(xt, base, v_out, mu_out):
    """``curve.peak_two_terms`` of every particle's curve base + chi_j of a (5, N) error cloud: the
    creep (km/h) and mu of its maximum, NaN where it has none (the MDIPF family's intervals)."""
    for j in range(xt.shape[1]):
        l0, l1, l2 = base[0] + xt[0, j], base[1] + xt[1, j], base[2] + xt[2, j]
        t1, t2 = base[3] + xt[3, j], base[4] + xt[4, j]
        v_out[j] = math.nan
        mu_out[j] = math.nan
        ratio = -(l2 * t2) / (l1 * t1) if l1 * t1 != 0.0 else -1.0
        if ratio > 0.0 and t1 != t2:
            v = math.log(ratio) / (t1 - t2)
            if v >= 0.0:
                e1, e2 = math.exp(t1 * v), math.exp(t2 * v)
                if l1 * t1 * t1 * e1 + l2 * t2 * t2 * e2 < 0.0:
                    v_out[j] = v
                    mu_out[j] = l0 + l1 * e1 + l2 * e2


@njit(**_JIT)
def weighted_moments(x, weights):
    """(mean, variance) of the weighted sample (weights normalised)."""
    m = 0.0
    for j in range(x.size):
        m += weights[j] * x[j]
    v = 0.0
    for j in range(x.size):
        d = x[j] - m
        v += weights[j] * d * d
    return m, v


@njit(**_JIT_EXACT)
def weighted_quantiles_hist(x, weights, qs, bins, counts, out):
    """The quantiles ``qs`` (ascending) of the weighted sample (x, weights), by a histogram of
    ``bins`` equal bins over [min x, max x] and linear interpolation inside a bin: one pass over
    the particles instead of a sort; the error is below a bin's width, (max - min) / bins."""
    lo = x[0]
    hi = x[0]
    for j in range(x.size):
        lo = min(lo, x[j])
        hi = max(hi, x[j])
    width = (hi - lo) / bins
    if not width > 0.0:
        for i in range(qs.size):
            out[i] = lo
        return
    counts[:bins] = 0.0
    total = 0.0
    for j in range(x.size):
        b = min(int((x[j] - lo) / width), bins - 1)
        counts[b] += weights[j]
        total += weights[j]
    acc = 0.0
    i = 0
    for b in range(bins):
        nxt = acc + counts[b]
        while i < qs.size and nxt >= qs[i] * total:
            frac = (qs[i] * total - acc) / counts[b] if counts[b] > 0.0 else 0.0
            out[i] = lo + (b + frac) * width
            i += 1
        acc = nxt
    while i < qs.size:
        out[i] = hi
        i += 1


# -- the form-free strategy (identifier/strategies/gp.py): its Kalman step and its peak draws ---------
@njit(**_JIT_EXACT)
def gp_update(z, P, b_idx, b_w, drive, q, sigma2, y, row0):
    """The strategy's filter step in place on z (1 + G) and P: predict with the curve's effect
    b = sum_k b_w[k] e_(b_idx[k]) (G; a few non-zeros, the interpolation weights of two creeps) and
    the torque's drive (a T_e), then update with the reading y; ``row0`` (1 + G) is scratch.  The
    same equations as ``GpStrategy._step`` (its module docstring), a pass each; b's sparsity makes
    the predict O(G), the update is O(G^2)."""
    g = z.size - 1
    nb = b_idx.size
    zb = 0.0
    bp0 = 0.0
    for k in range(nb):
        zb += b_w[k] * z[1 + b_idx[k]]
        bp0 += b_w[k] * P[0, 1 + b_idx[k]]
    z[0] += drive - zb                                              # omega^- = omega^ + a T_e - b^T m^
    for i in range(g):                                              # P-_0m = P_0m - P_mm b
        pb = 0.0
        for k in range(nb):
            pb += P[1 + i, 1 + b_idx[k]] * b_w[k]
        row0[1 + i] = P[0, 1 + i] - pb
    bpb = 0.0
    for k in range(nb):                                             # b^T P_mm b
        for l in range(nb):
            bpb += b_w[k] * P[1 + b_idx[k], 1 + b_idx[l]] * b_w[l]
    row0[0] = P[0, 0] - 2.0 * bp0 + bpb + q                         # P-_00
    for i in range(g):
        P[0, 1 + i] = row0[1 + i]
        P[1 + i, 0] = row0[1 + i]
    P[0, 0] = row0[0]
    s = row0[0] + sigma2                                            # S = P-_00 + sigma_y^2
    e = y - z[0]
    n = g + 1
    for i in range(n):                                              # z^ = z^- + K e,  K = P-_{:,0} / S
        z[i] += row0[i] / s * e
    for i in range(n):                                              # P = P- - K P-_{0,:}
        ki = row0[i] / s
        for j in range(n):
            P[i, j] -= ki * row0[j]
    return e


@njit(**_JIT_EXACT)
def _quantile_sorted(a, q):
    """numpy.quantile's default (linear) on an ascending ``a``."""
    pos = q * (a.size - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, a.size - 1)
    return a[lo] + (pos - lo) * (a[hi] - a[lo])


@njit(**_JIT_EXACT)
def gp_peak(z, P, i0, i1, sigmas, normals, log_x, upper_kmh, qs, root, cov, f, peak_mu, peak_creep, out):
    """``GpStrategy._region`` and ``peak_draws`` in one pass, then the quantiles: of the seen grid
    points i0..i1 (inclusive) keep those whose mean + ``sigmas`` sd reaches the highest mean -
    ``sigmas`` sd, with a neighbour each side; root <- the Cholesky factor of their covariance; draw
    d = mean + root normals[:k, d], its maximum's value and creep (a parabola in log creep through
    the maximum and its neighbours; ``upper_kmh`` where the maximum is the newest seen point i1);
    out (len(qs), 2) <- the quantiles qs of (peak mu, peak creep).  root, cov (G x G) and f
    (G x draws) are scratch (the draws row by row: contiguous, so the inner loop vectorises).
    Returns k, the number of points drawn."""
    floor = -1e300
    for i in range(i0, i1 + 1):
        sd = math.sqrt(max(P[1 + i, 1 + i], 0.0))
        floor = max(floor, z[1 + i] - sigmas * sd)
    lo, hi = i1, i0
    for i in range(i0, i1 + 1):
        sd = math.sqrt(max(P[1 + i, 1 + i], 0.0))
        if z[1 + i] + sigmas * sd >= floor:
            lo = min(lo, i)
            hi = max(hi, i)
    lo, hi = max(lo - 1, i0), min(hi + 1, i1)
    k = hi - lo + 1
    c = cov[:k, :k]
    for i in range(k):
        for j in range(k):
            c[i, j] = 0.5 * (P[1 + lo + i, 1 + lo + j] + P[1 + lo + j, 1 + lo + i])
        c[i, i] += 1e-12
    r = root[:k, :k]
    cholesky_lower(c, r)
    step = log_x[lo + 1] - log_x[lo] if k > 1 else 0.0
    n_draws = normals.shape[1]
    for i in range(k):                  # f[i, d] = mean_i + sum_j<=i root_ij normals_jd, row by row
        for d in range(n_draws):
            f[i, d] = z[1 + lo + i]
        for j in range(i + 1):
            rij = r[i, j]
            for d in range(n_draws):
                f[i, d] += rij * normals[j, d]
    for d in range(n_draws):
        best = 0
        for i in range(1, k):
            if f[i, d] > f[best, d]:
                best = i
        peak_mu[d] = f[best, d]
        off = 0.0
        if k >= 3:
            jj = min(max(best, 1), k - 2)
            if jj == best:
                denom = f[jj - 1, d] - 2.0 * f[jj, d] + f[jj + 1, d]
                if denom < 0.0:
                    off = min(max(0.5 * (f[jj - 1, d] - f[jj + 1, d]) / denom, -0.5), 0.5)
        peak_creep[d] = upper_kmh if lo + best == i1 else math.exp(log_x[lo + best] + off * step)
    a = np.sort(peak_mu)
    b = np.sort(peak_creep)
    for i in range(qs.size):
        out[i, 0] = _quantile_sorted(a, qs[i])
        out[i, 1] = _quantile_sorted(b, qs[i])
    return k


@njit(**_JIT_EXACT)
def exp_shape_fit(mu0_axis, a_axis, r_axis, peak_mu, peak_creep_kmh, v, m, theta):
    """theta (5) <- the curve of identifier/prior.py's form through (peak_creep_kmh, peak_mu) whose
    values at the creeps v are nearest m in least squares, over the grid mu(0) x a x r of the three
    axes (mu(0) capped at peak_mu / 2; ``GpStrategy.fit_shape``; prior.theta_from_phi's equations).
    Returns the flat index ((i_mu0 * len(a) + i_a) * len(r) + i_r) of the first minimum, as
    numpy.argmin over the grid ``meshgrid(mu0, a, r, indexing="ij")`` would.  The exponentials
    depend on (a, r) only, so they are computed once for all mu(0)."""
    best = 1e300
    best_i = 0
    na, nr = a_axis.size, r_axis.size
    e1 = np.empty(v.size)
    e2 = np.empty(v.size)
    for ia in range(na):
        a = a_axis[ia]
        t1 = -a / peak_creep_kmh
        e_a = math.exp(-a)
        for j in range(v.size):
            e1[j] = math.exp(t1 * v[j])
        for ir in range(nr):
            rr = r_axis[ir]
            t2 = rr * t1
            e_ra = math.exp((rr - 1.0) * a)
            for j in range(v.size):
                e2[j] = math.exp(t2 * v[j])
            for im in range(mu0_axis.size):
                mu0 = min(mu0_axis[im], 0.5 * peak_mu)
                l1 = (peak_mu - mu0) / ((e_a - 1.0) - (e_a - e_ra) / rr)
                l2 = -(l1 / rr) * e_ra
                l0 = mu0 - l1 - l2
                err = 0.0
                for j in range(v.size):
                    d = l0 + l1 * e1[j] + l2 * e2[j] - m[j]
                    err += d * d
                i = (im * na + ia) * nr + ir
                if err < best or (err == best and i < best_i):
                    best = err
                    best_i = i
                    theta[0], theta[1], theta[2], theta[3], theta[4] = l0, l1, l2, t1, t2
    return best_i


# -- the predictive peak estimate (identifier/peak_estimate.py) -------------------------------------------------
_LOG_2PI = math.log(2.0 * math.pi)


@njit(**_JIT_EXACT)
def peak_estimate_step(prec, b, logml, log_mass, start, count, n, log_prior, vp, kk, x, m, s2, prec0, b0, log_h,
                       log_1mh, kmax, step, h, lp, keep, dh, sv2):
    """One sample (x = |creep|, m = mu^) of identifier/peak_estimate.py's change-point recursion on rows 0..n-1 of the
    (kmax + 1, C) state, in place: a new run length is born in row n, then the least probable row is dropped
    when more than ``kmax`` remain.  Returns the number of rows.  ``h``, ``lp``: (C,) scratch; ``keep``: the
    weight the past keeps per sample (the estimator's memory); ``dh``: (C,) scratch for dh/dv; ``sv2``: the
    creep's noise variance (errors in the variable: (mean dh/dv)^2 sv2 joins the predictive variance)."""
    n_c = vp.size
    for c in range(n_c):
        xx = x / vp[c]
        k = kk[c]
        xp = xx ** (1.0 + k)
        den = k + xp
        h[c] = (1.0 + k) * xx / den
        dh[c] = (1.0 + k) * k * (1.0 - xp) / (den * den) / vp[c]
    mu0 = b0 / prec0
    mx = -np.inf
    for c in range(n_c):
        var = s2 + h[c] * h[c] / prec0 + mu0 * mu0 * dh[c] * dh[c] * sv2
        r = m - mu0 * h[c]
        v = -0.5 * (_LOG_2PI + math.log(var) + r * r / var)
        logml[n, c] = v
        if log_prior[c] + v > mx:
            mx = log_prior[c] + v
    acc = 0.0
    for c in range(n_c):
        acc += math.exp(log_prior[c] + logml[n, c] - mx)
    pred0 = mx + math.log(acc)
    mm = -np.inf
    for i in range(n):
        if log_mass[i] > mm:
            mm = log_mass[i]
    acc = 0.0
    for i in range(n):
        acc += math.exp(log_mass[i] - mm)
    mass_all = mm + math.log(acc)
    for i in range(n):
        mx1 = -np.inf
        mx2 = -np.inf
        for c in range(n_c):
            p = prec[i, c]
            mean = b[i, c] / p
            var = s2 + h[c] * h[c] / p + mean * mean * dh[c] * dh[c] * sv2
            r = m - mean * h[c]
            v = -0.5 * (_LOG_2PI + math.log(var) + r * r / var)
            lp[c] = v
            a1 = log_prior[c] + logml[i, c]
            if a1 > mx1:
                mx1 = a1
            if a1 + v > mx2:
                mx2 = a1 + v
        s1 = 0.0
        s2_ = 0.0
        for c in range(n_c):
            a1 = log_prior[c] + logml[i, c]
            s1 += math.exp(a1 - mx1)
            s2_ += math.exp(a1 + lp[c] - mx2)
        log_mass[i] += log_1mh + (mx2 + math.log(s2_)) - (mx1 + math.log(s1))
        for c in range(n_c):
            logml[i, c] = keep * logml[i, c] + lp[c]
            prec[i, c] = prec0 + keep * (prec[i, c] - prec0) + h[c] * h[c] / s2
            b[i, c] = b0 + keep * (b[i, c] - b0) + h[c] * m / s2
        count[i] += 1
    for c in range(n_c):
        prec[n, c] = prec0 + h[c] * h[c] / s2
        b[n, c] = b0 + h[c] * m / s2
    log_mass[n] = log_h + mass_all + pred0
    start[n] = step
    count[n] = 1
    n += 1
    if n > kmax:
        j = 0
        for i in range(1, n):
            if log_mass[i] < log_mass[j]:
                j = i
        last = n - 1
        if j != last:
            for c in range(n_c):
                prec[j, c] = prec[last, c]
                b[j, c] = b[last, c]
                logml[j, c] = logml[last, c]
            log_mass[j] = log_mass[last]
            start[j] = start[last]
            count[j] = count[last]
        n -= 1
    mm = -np.inf
    for i in range(n):
        if log_mass[i] > mm:
            mm = log_mass[i]
    acc = 0.0
    for i in range(n):
        acc += math.exp(log_mass[i] - mm)
    norm = mm + math.log(acc)
    for i in range(n):
        log_mass[i] -= norm
    return n


@njit(**_JIT_EXACT)
def peak_estimate_publish(prec, b, logml, log_mass, n, log_prior, n_k, log_grid, marg, out):
    """The published figures of identifier/peak_estimate.py's mixture over rows 0..n-1: out = (peak creep 5, 50,
    95 % quantiles, peak mu mean and sd, the most probable row).  ``marg``: (grid,) scratch."""
    n_c = log_prior.size
    for j in range(marg.size):
        marg[j] = 0.0
    m1 = 0.0
    m2 = 0.0
    total = 0.0
    best = 0
    for i in range(n):
        if log_mass[i] > log_mass[best]:
            best = i
        mx = -np.inf
        for c in range(n_c):
            a = log_prior[c] + logml[i, c]
            if a > mx:
                mx = a
        acc = 0.0
        for c in range(n_c):
            acc += math.exp(log_prior[c] + logml[i, c] - mx)
        lse = mx + math.log(acc)
        for c in range(n_c):
            w = math.exp(log_mass[i] + log_prior[c] + logml[i, c] - lse)
            marg[c // n_k] += w
            mean = b[i, c] / prec[i, c]
            m1 += w * mean
            m2 += w * (mean * mean + 1.0 / prec[i, c])
            total += w
    m1 /= total
    m2 /= total
    for j in range(marg.size):
        marg[j] /= total
    for q_i in range(3):
        q = 0.05 if q_i == 0 else (0.5 if q_i == 1 else 0.95)
        cum = 0.0
        prev_mid = -1.0
        val = log_grid[log_grid.size - 1]
        for j in range(marg.size):
            mid = cum + 0.5 * marg[j]
            if mid >= q:
                if j == 0 or mid <= prev_mid:
                    val = log_grid[j]
                else:
                    val = log_grid[j - 1] + (log_grid[j] - log_grid[j - 1]) * (q - prev_mid) / (mid - prev_mid)
                break
            prev_mid = mid
            cum += marg[j]
        out[q_i] = math.exp(val)
    out[3] = m1
    out[4] = math.sqrt(max(m2 - m1 * m1, 0.0))
    out[5] = best


def _warm_calls() -> list:
    """(kernel name, a call that compiles it on tiny inputs or loads it from the cache), in order."""
    xt = np.zeros((5, 4))
    xt[:, 1] = 1e-3
    w = np.full(4, 0.25)
    ll, tmp = np.empty(4), np.empty((2, 4))
    v = np.linspace(0.5, 1.0, 6)
    x = np.array([0.0, 0.1, -0.1, -0.5, -1.0])
    lo, hi = x - 0.1, x + 0.1
    c = np.full(4, 0.1)
    u16 = np.ascontiguousarray(np.random.default_rng(0).standard_normal((16, 5)).T)
    th16 = np.empty((5, 16))
    ps = (np.ones((3, 4)), np.zeros((3, 4)), np.zeros((3, 4)), np.zeros(3), np.zeros(3, np.int64),
          np.zeros(3, np.int64))
    grid = np.ones(4)
    return [
        ("peak_estimate_step", lambda: peak_estimate_step(*ps, 1, np.zeros(4), grid, grid, 0.5, 0.1, 1e-4, 1.0, 0.0,
                                                          -7.0, -1e-3, 2, 0, np.empty(4), np.empty(4), 1.0, np.empty(4), 1e-4)),
        ("peak_estimate_publish", lambda: peak_estimate_publish(*ps[:4], 1, np.zeros(4), 1, np.zeros(4),
                                                                np.empty(4), np.empty(6))),
        ("rownorm_propagate", lambda: rownorm_propagate(xt, w, np.zeros((5, 4)), np.empty((5, 4)), np.empty((5, 4)))),
        ("log_likelihood", lambda: log_likelihood(xt, np.zeros(5), 1.0, 0.1, -0.5, ll, tmp)),
        ("reweigh", lambda: reweigh(ll, w, np.empty(4))),
        ("filter_step", lambda: filter_step(
            xt, w, np.zeros((5, 4)), np.empty((5, 4)), np.empty((5, 4)), np.zeros(5), 1.0, 0.1, -0.5, np.zeros(5),
            np.ones(5), True, ll, np.empty(4), tmp)),
        ("vexp", lambda: vexp(np.zeros(4))),
        ("weighted_mean", lambda: weighted_mean(xt, w, np.empty(5))),
        ("systematic_resample", lambda: systematic_resample(w, 0.5, np.empty(4, np.intp))),
        ("take_columns", lambda: take_columns(xt, np.zeros(4, np.intp), np.empty((5, 4)))),
        ("recentre", lambda: recentre(np.zeros((5, 4)), np.zeros(5), -np.ones(5), np.ones(5), True)),
        ("bounded_lm", lambda: bounded_lm(x, lo, hi, v, np.full(6, 0.1), np.zeros((0, 0)), 2, 1e-10)),
        ("bounded_lm", lambda: bounded_lm(x, lo, hi, v, np.full(6, 0.1), np.eye(6), 2, 1e-10)),
        ("grid_best", lambda: grid_best(
            np.tile(np.eye(3), (4, 1, 1)), np.ones((4, 3)), 1.0, np.full((4, 2), -0.5), lo, hi)),
        ("grid_add", lambda: grid_add(
            np.full((4, 2), -0.5), 1.0, 0.1, np.empty((4, 3)), np.zeros((4, 3, 3)), np.zeros((4, 3)))),
        ("bayes_step", lambda: bayes_step(
            c, c, -c, -c, -c, np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4), np.full(4, 0.25),
            1.0, 0.0, 1.0, 1e-4, 1.0, 1.0, 0.5, 0.0, np.empty(2))),
        ("bayes_rerun", lambda: bayes_rerun(
            c, c, -c, -c, -c, np.ones(3), np.zeros(3), np.ones(3), np.full(3, 1e-4), np.full(3, 0.5), np.ones(3),
            np.zeros(3), 1.0, np.empty(4), np.empty(4), np.empty(4), np.empty(4))),
        ("bayes_curves", lambda: bayes_curves(
            u16, np.zeros(5), np.ones(5), np.array([False, True, False, True, True]), np.empty((5, 16)),
            np.empty(16), np.empty(16), np.empty(16), np.empty(16), np.empty(16))),
        ("weighted_moments", lambda: weighted_moments(u16[0], np.full(16, 1 / 16))),
        ("weighted_covariance5", lambda: weighted_covariance5(u16, np.full(16, 1 / 16), np.empty((5, 5)))),
        ("cholesky_lower", lambda: cholesky_lower(np.eye(5), np.empty((5, 5)))),
        ("baseline_stats", lambda: baseline_stats(np.ones((3, 16)), 20)),
        ("bayes_curves", lambda: bayes_curves(
            u16, np.zeros(5), np.ones(5), np.array([False, True, False, True, True]), np.empty((5, 16)), *th16)),
        ("bayes_move", lambda: bayes_move(
            u16.copy(), np.empty((5, 16)), *th16, np.zeros(16), np.zeros(16), np.zeros(16), np.zeros(16), 0, 4,
            np.eye(5), np.zeros((5, 16)), np.full(16, 0.5), np.zeros(5), np.ones(5), np.array([False, True, False,
            True, True]), np.ones(3), np.zeros(3), np.ones(3), np.full(3, 1e-4), np.full(3, 0.5), np.ones(3),
            np.zeros(3), 1.0)),
        ("cloud_peaks", lambda: cloud_peaks(
            np.zeros((5, 4)), np.array([0.0, 1.0, -1.0, -0.54, -1.2]), np.empty(4), np.empty(4))),
        ("bayes_mu_at", lambda: bayes_mu_at(u16[0], u16[1], u16[2], u16[3], u16[4], 0.5, np.empty(16))),
        ("weighted_quantiles_hist", lambda: weighted_quantiles_hist(
            u16[0], np.full(16, 1 / 16), np.array([0.05, 0.5, 0.95]), 64, np.empty(64), np.empty(3))),
        ("gp_update", lambda: gp_update(
            np.zeros(4), np.eye(4), np.array([0, 1, 1, 2]), np.full(4, 0.1), 0.0, 1e-6, 1e-4, 0.0, np.empty(4))),
        ("gp_peak", lambda: gp_peak(
            np.zeros(4), np.eye(4), 0, 2, 4.0, np.zeros((3, 4)), np.arange(3.0), 3.0, np.array([0.1, 0.5, 0.9]),
            np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 4)), np.empty(4), np.empty(4), np.empty((3, 2)))),
        ("exp_shape_fit", lambda: exp_shape_fit(
            np.zeros(2), np.ones(2), np.full(2, 2.0), 0.1, 1.0, np.ones(3), np.ones(3), np.empty(5))),
    ]


def warm_up(progress=None) -> None:
    """Compile (or load from the cache) every kernel now, e.g. before the fault, not on the first
    sample; once per process.  ``progress(done, total, name)``, when given, is called before each kernel."""
    global _warmed
    if not AVAILABLE or _warmed:
        return
    calls = _warm_calls()
    for i, (name, call) in enumerate(calls):
        if progress is not None:
            progress(i, len(calls), name)
        call()
    if progress is not None:
        progress(len(calls), len(calls), "")
    _warmed = True
