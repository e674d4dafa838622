"""The compiled kernels (identifier/kernels.py) against the numpy reference pieces (identifier/pf.py,
identifier/strategies/nlls.py), and the strategies run both ways on the same samples."""
import math

import numpy as np
import pytest

from identifier import kernels, make_strategy, pf
from identifier.strategies.nlls import GridAccumulator

from .test_strategies import FFCC_A, feed, samples_spanning_peak, settings

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed (pip install numba)")

P, N = 5, 700
BASE = np.array([0.0, 1.0, -1.0, -0.54, -1.2])


def cloud(seed=0, spread=(0.003, 0.02, 0.02, 0.03, 0.03), n=N):
    """A (len(spread), n) cloud, normalised weights and the generator that drew them."""
    spread = np.asarray(spread, float)
    rng = np.random.default_rng(seed)
    xt = np.ascontiguousarray(rng.standard_normal((spread.size, n)) * spread[:, None])
    w = rng.random(n)
    return xt, w / w.sum(), rng


def assert_filter_step_is_the_reference_pieces(xt, w, noise, base, lo, hi, use_box):
    """kernels.filter_step against pf's pieces one after the other (move, clip, likelihood, weights)."""
    p, n = xt.shape
    v, mu, g = 0.9, 0.12, 0.002
    out, ll, w_out = np.empty((p, n)), np.empty(n), np.empty(n)
    ess = kernels.filter_step(xt, w, noise, out, np.empty((p, n)), base, v, mu, -0.5 / g ** 2, lo, hi, use_box, ll,
                              w_out, np.empty(((p - 1) // 2, n)))
    moved = pf.propagate(xt.T, pf.correlation_transition(xt.T, w, "rownorm"), np.ones(p), noise=noise.T)
    if use_box:
        moved = pf.project_to_box(moved, lo, hi, base, v, mu, np.ones(p), g, "clip")
        assert np.all(out >= lo[:, None]) and np.all(out <= hi[:, None])
    np.testing.assert_allclose(out, moved.T, rtol=1e-12, atol=1e-15)
    ref_ll = pf.log_likelihood(moved, base, v, mu, g)
    np.testing.assert_allclose(ll, ref_ll, rtol=1e-9, atol=1e-9)
    ref_w = pf.normalise(np.log(w) + ref_ll)
    np.testing.assert_allclose(w_out, ref_w, rtol=1e-8, atol=1e-300)
    assert ess == pytest.approx(pf.ess(ref_w), rel=1e-9)


def test_vexp_matches_numpy_exp_to_an_ulp_and_keeps_the_special_values():
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(-708.0, 709.0, 50_000), rng.uniform(-60.0, 1.0, 50_000),
                        [0.0, -0.0, 1e-300, -1e-300, 1.0, math.log(2.0)]])
    got = kernels.vexp(x.copy())
    ref = np.exp(x)
    assert np.max(np.abs(got - ref) / ref) <= 2.5e-16          # about 1 ulp
    special = np.array([np.nan, np.inf, -np.inf, -800.0, 710.0, 1e300, -1e300])
    got = kernels.vexp(special.copy())
    assert np.isnan(got[0]) and got[1] == np.inf and got[2] == 0.0 and got[3] == 0.0
    assert got[4] == np.inf and got[5] == np.inf and got[6] == 0.0


@pytest.mark.parametrize("use_box", [False, True])
def test_filter_step_equals_the_reference_pieces(use_box):
    xt, w, rng = cloud(2)
    noise = np.ascontiguousarray(rng.standard_normal((P, N)) * 1e-3)
    lo, hi = np.array([-0.004, -0.02, -0.02, -0.03, -0.03]), np.array([0.004, 0.02, 0.02, 0.03, 0.03])
    assert_filter_step_is_the_reference_pieces(xt, w, noise, BASE, lo, hi, use_box)


def test_filter_step_hands_degenerate_clouds_back_to_the_reference_path():
    xt, w, _ = cloud(3)
    args = dict(noise=np.zeros((P, N)), out=np.full((P, N), 7.0), d=np.empty((P, N)))
    flat = xt.copy()
    flat[2] = 0.0                                             # a dimension without spread: no correlation
    ess = kernels.filter_step(flat, w, args["noise"], args["out"], args["d"], BASE, 1.0, 0.1, -1e5, BASE, BASE,
                              False, np.empty(N), np.empty(N), np.empty((2, N)))
    assert ess == -1.0 and np.all(args["out"] == 7.0)           # nothing written
    bad = xt.copy()
    bad[1, 5] = np.inf
    ess = kernels.filter_step(bad, w, args["noise"], args["out"], args["d"], BASE, 1.0, 0.1, -1e5, BASE, BASE,
                              False, np.empty(N), np.empty(N), np.empty((2, N)))
    assert ess in (-1.0, -2.0)
    far = xt.copy()                                           # every likelihood underflows to 0 (log: -inf)
    ess = kernels.filter_step(far, w, args["noise"], args["out"], args["d"], BASE, 1.0, 50.0, -1e308, BASE, BASE,
                              False, np.empty(N), np.empty(N), np.empty((2, N)))
    assert ess == -3.0


def test_systematic_resampling_picks_the_reference_ancestors():
    for seed in range(5):
        _, w, rng = cloud(seed)
        w = w ** 3
        w /= w.sum()
        u0 = rng.random()
        idx = kernels.systematic_resample(w, u0, np.empty(N, np.intp))
        ref = pf.systematic_counts_resample(w, u0, np.arange(N))
        assert np.array_equal(idx, ref)
        taken = np.empty((P, N))
        xt = np.ascontiguousarray(np.arange(P * N, dtype=float).reshape(P, N))
        kernels.take_columns(xt, idx, taken)
        assert np.array_equal(taken, xt[:, idx])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_prelim_reaches_the_numpy_prelim(seed):
    rng = np.random.default_rng(seed)
    v = np.sort(rng.uniform(0.5, 1.2, 6))
    from identifier.curve import mu_model
    y = mu_model(v, FFCC_A) + rng.normal(0.0, 7e-4, 6)
    radius = np.array([0.01, 0.6, 0.6, 0.05, 0.05])
    xs = []
    for compiled in (False, True):
        acc = GridAccumulator(BASE, radius, 5, 8, 64, compiled=compiled)
        for a, b in zip(v, y):
            acc.add(a, b)
        job = acc.job(v, y)
        while not job.done:
            job.step()
        xs.append(job.x)
    np.testing.assert_allclose(xs[1], xs[0], rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("name", ["mdipf", "proposed", "proposed_mu0", "mdipf_raw", "proposed_fast", "proposed_oa"])
def test_a_strategy_gives_the_same_curve_compiled_and_in_numpy(name):
    """The compiled step, resampling and prelim (the default) against the numpy reference path
    (``compiled = False``): same corrections, same confirmation, the same curve up to rounding."""
    samples = samples_spanning_peak(300)
    runs = []
    for compiled in (False, True):
        strat = make_strategy(name, settings(options={name: {"compiled": compiled}}), seed=11)
        runs.append((strat, [(e.kind, e.correction) for e in feed(strat, samples)]))
    (ref, ev_ref), (fast, ev_fast) = runs
    assert fast._compiled and not ref._compiled
    assert ev_fast == ev_ref and fast.confirmed == ref.confirmed
    np.testing.assert_allclose(fast.theta, ref.theta, rtol=0, atol=1e-7)


# -- sizes other than the five-parameter model (the generic kernels) and the step's edge cases ----
BASES = {3: np.array([0.0, 1.0, -1.0]), 5: BASE, 7: np.array([0.0, 1.0, -1.0, 0.3, -0.54, -1.2, -2.5])}


def cloud_p(p, seed=0, n=N):
    """``cloud`` of p dimensions (spread 0.003 for lambda0, 0.02 for the others)."""
    return cloud(seed, np.r_[0.003, np.full(p - 1, 0.02)], n)


@pytest.mark.parametrize("p", [3, 7])
@pytest.mark.parametrize("use_box", [False, True])
def test_filter_step_of_other_sizes_equals_the_reference_pieces(p, use_box):
    xt, w, rng = cloud_p(p, 4)
    noise = np.ascontiguousarray(rng.standard_normal((p, N)) * 1e-3)
    lo, hi = np.full(p, -0.02), np.full(p, 0.02)
    lo[0], hi[0] = -0.004, 0.004
    assert_filter_step_is_the_reference_pieces(xt, w, noise, BASES[p], lo, hi, use_box)


@pytest.mark.parametrize("p", [3, 5, 7])
def test_the_separate_kernels_equal_the_reference_pieces(p):
    """rownorm_propagate, log_likelihood and reweigh (the strategies' unfused path) one by one."""
    xt, w, rng = cloud_p(p, 5)
    base = BASES[p]
    noise = np.ascontiguousarray(rng.standard_normal((p, N)) * 1e-3)
    out = np.empty((p, N))
    assert kernels.rownorm_propagate(xt, w, noise, out, np.empty((p, N)))
    moved = pf.propagate(xt.T, pf.correlation_transition(xt.T, w, "rownorm"), np.ones(p), noise=noise.T)
    np.testing.assert_allclose(out, moved.T, rtol=1e-12, atol=1e-15)
    ll = np.empty(N)
    assert kernels.log_likelihood(out, base, 0.8, 0.12, -0.5 / 0.002 ** 2, ll, np.empty(((p - 1) // 2, N)))
    ref_ll = pf.log_likelihood(moved, base, 0.8, 0.12, 0.002)
    np.testing.assert_allclose(ll, ref_ll, rtol=1e-11, atol=1e-10)
    w_out = np.empty(N)
    ess = kernels.reweigh(ll, w, w_out)
    ref_w = pf.normalise(np.log(w) + ref_ll)
    np.testing.assert_allclose(w_out, ref_w, rtol=1e-8, atol=1e-300)
    assert ess == pytest.approx(pf.ess(ref_w), rel=1e-9)
    bad = ll.copy()
    bad[7] = np.nan                                            # NaN, or no finite maximum: the caller's log path
    assert kernels.reweigh(bad, w, w_out) == -1.0
    assert kernels.reweigh(np.full(N, -np.inf), w, w_out) == -1.0


def test_the_steps_likelihood_is_the_curve_at_its_own_clipped_cloud():
    """The five-parameter step evaluates the curve (its inlined exp) in the same pass as the move:
    log_lik must be the likelihood of the cloud it leaves in ``out``, to rounding."""
    xt, w, rng = cloud(6)
    noise = np.ascontiguousarray(rng.standard_normal((P, N)) * 1e-3)
    lo, hi = np.array([-0.004, -0.02, -0.02, -0.03, -0.03]), np.array([0.004, 0.02, 0.02, 0.03, 0.03])
    out, ll = np.empty((P, N)), np.empty(N)
    kernels.filter_step(xt, w, noise, out, np.empty((P, N)), BASE, 0.7, 0.13, -0.5 / 0.002 ** 2, lo, hi, True, ll,
                        np.empty(N), np.empty((2, N)))
    np.testing.assert_allclose(ll, pf.log_likelihood(out.T, BASE, 0.7, 0.13, 0.002), rtol=1e-11, atol=1e-10)


@pytest.mark.parametrize("use_box", [False, True])
def test_a_non_finite_move_leaves_the_unclipped_moved_cloud(use_box):
    """Code -2: ``out`` holds the moved cloud, not clipped, for the caller's reference path."""
    xt, w, rng = cloud(7)
    noise = np.ascontiguousarray(rng.standard_normal((P, N)) * 1e-2)
    noise[3, 11] = np.inf
    lo, hi = np.full(P, -1e-3), np.full(P, 1e-3)              # most particles lie outside this box
    out = np.empty((P, N))
    ess = kernels.filter_step(xt, w, noise, out, np.empty((P, N)), BASE, 1.0, 0.1, -1e5, lo, hi, use_box,
                              np.empty(N), np.empty(N), np.empty((2, N)))
    assert ess == -2.0
    with np.errstate(invalid="ignore"):
        moved = pf.propagate(xt.T, pf.correlation_transition(xt.T, w, "rownorm"), np.ones(P), noise=noise.T).T
    assert out[3, 11] == np.inf and np.sum(~np.isfinite(out)) == 1
    np.testing.assert_allclose(out, moved, rtol=1e-12, atol=1e-15)


def resample_cases():
    """(weights, u0): the filter's kind of weights and the edges of resampling by counts."""
    rng = np.random.default_rng(8)
    for n in (1, 2, 3, 4, 5, 7, 8, 9, 33, 1000):
        for _ in range(4):
            yield rng.random(n) ** 3, rng.random()
    for n in (100, 1000):
        z = rng.standard_normal(n)
        yield np.exp(-2.0 * z * z), rng.random()                 # the step's weights (ESS ~ N / 2)
        yield np.exp(-40.0 * z * z), rng.random()                # a low ESS: many particles with > 4 copies
        one = np.zeros(n)
        one[n // 3] = 1.0
        yield one, rng.random()                                  # all copies to one particle, N of them
        yield np.r_[np.zeros(n - 1), 1.0], rng.random()          # ... to the last one
        yield np.r_[1.0, np.zeros(n - 1)], 0.0                   # ... to the first one, u0 = 0
        sparse = np.where(rng.random(n) < 0.05, rng.random(n), 0.0)
        yield sparse, rng.random()
        yield np.full(n, 1.0), rng.random()                      # every particle once


@pytest.mark.parametrize("short", [False, True])
def test_systematic_resampling_picks_the_reference_ancestors_at_the_edges(short):
    """Counts above the kernel's block of copies, runs ending in its last slots, zero weights, and
    (``short``) cumulative sums that round below 1, where the last particle takes what remains."""
    for w, u0 in resample_cases():
        w = w / w.sum()
        if short:
            w = w * (1.0 - 1e-9)
        idx = kernels.systematic_resample(w, u0, np.full(w.size, -1, np.intp))
        assert np.array_equal(idx, pf.systematic_counts_resample(w, u0, np.arange(w.size))), (w.size, u0)


@pytest.mark.parametrize("p", [3, 5])
def test_take_columns_keeps_the_ancestors_columns(p):
    xt = np.ascontiguousarray(np.arange(p * N, dtype=float).reshape(p, N))
    idx = np.sort(np.random.default_rng(9).integers(0, N, N))
    taken = np.empty((p, N))
    kernels.take_columns(xt, idx, taken)
    assert np.array_equal(taken, xt[:, idx])


@pytest.mark.parametrize("p", [3, 5])
def test_weighted_mean_is_weights_at_the_cloud(p):
    xt, w, _ = cloud_p(p, 10)
    xt += np.arange(p)[:, None]                               # means far from 0, as the model's errors are not
    out = kernels.weighted_mean(xt, w, np.empty(p))
    np.testing.assert_allclose(out, w @ xt.T, rtol=1e-13, atol=1e-16)


@pytest.mark.parametrize("use_box", [True, False])
def test_recentre_is_numpys_shift_and_clip_to_the_bit(use_box):
    rng = np.random.default_rng(11)
    xt = rng.standard_normal((5, 1000)) * 0.05
    shift = rng.standard_normal(5) * 0.01
    lo, hi = -np.full(5, 0.04), np.full(5, 0.03)
    expected = xt - shift[:, None]
    if use_box:
        expected = np.minimum(np.maximum(expected, lo[:, None]), hi[:, None])
    got = xt.copy()
    kernels.recentre(got, shift, lo, hi, use_box)
    assert np.array_equal(got, expected)


def test_compiled_lattice_sums_are_numpys():
    radius = np.array([0.01, 0.6, 0.6, 0.05, 0.05])
    accs = [GridAccumulator(BASE, radius, 5, 8, 8, compiled=c) for c in (False, True)]
    for a, b in zip(np.linspace(0.4, 1.3, 6), np.linspace(0.08, 0.15, 6)):
        for acc in accs:
            acc.add(float(a), float(b))
    ref, fast = accs
    assert fast.compiled and not ref.compiled
    for name in ("phi", "a", "b"):
        np.testing.assert_allclose(getattr(fast, name), getattr(ref, name), rtol=1e-13, atol=0)
    assert fast.tt == ref.tt and fast.count == ref.count == 6
