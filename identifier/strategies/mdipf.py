"""MDIPF: NLLS preliminary fit, then particle-filter corrections of the curve (paper §3.3, §9).

Window 1 (L samples): preliminary fit theta_pre by trust-region NLLS (§3.2).  Every later sample
steps a particle filter over *error* vectors chi = (xi0, xi1..n, gamma1..n) added to the current
parameters theta_{Q-1}; at the end of each window the weighted mean chi^_Q gives
theta_Q = theta_{Q-1} + chi^_Q (correction Q), and the multi-level evaluation of ``Strategy``
compares chi^_Q with chi^_{Q-1}.  ``ProposedStrategy`` (proposed.py) adds the dynamic projection box.

Tuning: ``settings.options[NAME]`` (scenario ``[identifier.options.NAME]``) overrides any key of
``DEFAULTS`` and the shared ``window_samples`` (L), ``k_pe``, ``c_lw``, ``c_up``.  Per-dimension
standard deviations are three numbers (lambda0, every lambda_i, every tau_i) or 2n+1 numbers.
Defaults (chosen with ``hil bench identify`` on FFCC-a and FFCC-b; the figures are in
docs/design/identifier.md): L = 6 (the least the SE of eq. 29 allows; fewer samples per window is
the largest RT lever); K_PE = 1e-4, c_lw = c_up = 3; N = 1000 (the issue's reference size); B, G,
initial spread: RT and peak errors moved less than their seed-to-seed spread, so the values are the
physical scales (G ~ 2x the mu^ noise, the NLLS residual; B ~ 1/6 of the initial spread so the
cloud can move one initial sigma per window).

The preliminary fit (``prelim_radius``): the paper's trust-region NLLS bounds each step by rho;
we also keep the solution within the TCU's prior curve (NFCC-0, ``initial_guess``) +- the radius.
Six early-stage samples cannot fix five parameters: unbounded, the prelim's peak creep is off by
200-700 % and the particle filter, which only corrects around it, confirms that wrong curve
(``prelim_radius = None`` keeps the unbounded reading).  The default radius lets lambda_i move by
0.6 (the fault curves halve NFCC-0's lambdas) and tau_i by 0.05.

Choices the paper leaves open (alternatives behind options):
- Theta's stability: ``stabiliser`` (pf.STABILISERS), default row-normalised correlation.
- resampling: ``resampler`` (systematic by default) whenever ESS < ``ess_fraction`` * N.
- what chi^_0 is: the preliminary fit corrects nothing, so chi^_0 = 0 and J_EF(1) = |chi^_1|^2
  (``j_ef_from_prelim``); with False the first J_EF is at Q = 2 (one window later).
- between corrections the cloud is re-centred on the new theta (chi <- chi - chi^_Q), so it keeps
  its learnt spread and weights; ``reset_cloud`` re-draws it from the initial spread instead.
- random numbers are drawn when the strategy is built (before the fault, when the TCU is idle):
  the first ``noise_block`` samples' transition noise, the initial cloud and ``noise_block``
  resampling uniforms, in the order the filter would have drawn them within the block (so results
  are unchanged); past the block, one draw per sample (no burst of a whole block on one sample;
  runs that long draw a different stream).
- the cloud is kept as a (P, N) C-contiguous array ``_xt`` (``particles`` is its (N, P) view),
  so every pass over it is over contiguous rows, also after resampling.
- ``prelim_solver``: how the bounded prelim problem is solved (the same objective and bounds).
  "grid" (default, ``nlls.fit_curve_grid``): variable projection on a 5 x 5 lattice of tau in
  the box (lambda by one batched linear solve per lattice point), then <= 8 LM steps; "trf":
  scipy's trust-region-reflective (the paper's trust region, literally); "lm": LM from the prior.
  "grid" reaches the same least-squares cost as "trf" in a fraction of the time; the 6-sample
  problem is a flat valley, so the two stop at different thetas of equal cost.  "lm" from the
  prior stops early in the valley: kept only as a measured alternative (the comparison:
  docs/design/identifier.md).

Cost per sample (the TCU has one sampling period, 1 ms, per sample; ``hil bench identify`` reports
the cost of every fed sample, and its p99 is in effect a run's costliest sample).  Work that runs
once per window runs on cold caches (2-3x its cost in a loop), so the window-end work is spread:
- ``compiled`` (default True): the filter step is one call of ``kernels.filter_step`` (numba:
  Theta, propagation, the "clip" box, likelihood with an inlined exp, reweighing), then
  systematic resampling by ``kernels.systematic_resample`` / ``take_columns`` when ESS is low.
  Around the windows:
  - window 1: each sample adds to the prelim's tau lattice (``kernels.grid_add``); its last sample
    solves the lattice (``kernels.grid_best``), the next runs the LM polish (``kernels.bounded_lm``,
    one call), the one after opens the filter (the prelim's correction event moves two samples,
    2 ms, later); the filter's first step comes on the sample after, alone, then
    ``catch_up_per_sample`` steps per sample until it has caught up (results unchanged: the same
    steps, later);
  - a correction: its sample computes chi^ (``kernels.weighted_mean``), theta and J_EF and emits
    the event; the box contraction, the re-centring and the clip into the new box wait for the
    next step (``_defer_recentre``; one pass, ``kernels.recentre``), the candidate's SE for the
    next window's 2nd sample (``Strategy``);
  - random numbers (noise, first cloud, resampling uniforms) are drawn before the fault.
  The costliest samples are then the opening and the first step; what is left of "cold" is taken
  off by the TCU's drill (identifier/drill.py, ``keeps_warm`` below).  The costs before and after
  this spreading: docs/design/identifier.md.  Variants with their own step (observer-aware, mu(0) = 0,
  other Theta or projections) use the compiled pieces where their step is the plain one, and
  re-centre at the correction.
- ``compiled = False``, the numpy reference path: the filter step (``_move``, ``_log_likelihood``,
  ``_weigh``) works on the (P, N) cloud with
  preallocated buffers and few numpy calls (at N = 1000 a call's overhead, not its arithmetic, is
  most of the cost): Theta by ``pf.rownorm_transition`` (the row-normalised correlation without
  forming it), the weights as w_prev exp(ll - max ll) / sum (no logarithms; log weights only if
  that underflows), systematic resampling by counts (``pf.systematic_counts_resample``) only when
  ESS < ``ess_fraction`` N.  These equal the reference pieces of identifier/pf.py up to rounding.
  Its "grid" prelim is spread (``prelim_polish_per_sample`` > 0, default 3): the lattice's normal
  equations are summed as window 1's samples arrive (``nlls.GridAccumulator``), the lattice is
  solved on window 1's last sample, the LM polish runs 3 iterations per sample on the next
  samples, and on the sample after the polish the filter opens (cloud drawn, the prelim's
  correction event) and steps through the samples fed meanwhile, in order, ``catch_up_at_open``
  of them on that sample and ``catch_up_per_sample`` per later sample until it has caught up (a
  window's correction first finishes the queue).  The filter's steps are exactly those it would
  have made on time (same results as ``prelim_polish_per_sample = 0`` up to rounding), only
  later; what moves is the prelim's correction event, 4 samples (4 ms) after window 1 ends on
  the bench's data (the polish takes its 8 iterations there).  RT, J_EF and the confirmation are
  unchanged.  0 keeps the whole prelim on window 1's last sample.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from .. import pf
from .base import Strategy, cloud_peak_intervals, load_kernels
from .nlls import GridAccumulator, fit_curve, fit_curve_grid, fit_curve_lm

DEFAULTS = {
    "particles": 1000,                        # N
    "init_std": [0.003, 0.02, 0.03],          # initial cloud spread (lambda0, lambda_i, tau_i)
    "transition_std": [0.0005, 0.003, 0.005], # B: sqrt of the diagonal of the transition noise
    "noise_std": 0.002,                       # G: sqrt of the measurement-noise variance (mu units)
    "stabiliser": "rownorm",                  # Theta: pf.STABILISERS
    "resampler": "systematic",                # pf.RESAMPLERS
    "ess_fraction": 0.5,                      # resample when ESS < this * N
    "j_ef_from_prelim": True,                 # chi^_0 = 0 counts for J_EF(1)
    "reset_cloud": False,                     # re-draw (True) or re-centre (False) the cloud after a correction
    "noise_block": 32,                        # transition-noise draws made ahead, in blocks of this many samples
    "prelim_radius": [0.01, 0.6, 0.05],       # prelim kept within the prior curve +- this (None: unbounded)
    "filter_prelim_window": False,            # True: correction 1 filters the prelim's own window (beyond the paper)
    "prelim_solver": "grid",                  # "trf": scipy trust-region-reflective; "grid": nlls.fit_curve_grid;
                                              # "lm": nlls.bounded_lm from the prior curve (both numpy)
    "prelim_iterations": 8,                   # iteration cap of the "lm" prelim / LM polish of "grid"
    "prelim_grid": 5,                         # tau lattice of the "grid" prelim (per tau)
    "prelim_polish_per_sample": 3,            # "grid" prelim: LM polish iterations per sample, spread over the
                                              # samples after window 1 (compiled: > 0 puts the whole polish on
                                              # the next sample; 0: the whole prelim on window 1's last sample)
    "catch_up_per_sample": 2,                 # filter steps per sample while catching up after a spread prelim
    "catch_up_at_open": 1,                    # ... and on the sample the filter opens on (L = 6 needs it to
                                              # catch up before window 2 closes)
    "publish_latest": False,                  # beyond the paper (proposed_latest): confirm the filter's estimate
                                              # after the confirmation window instead of the checked candidate
    "compiled": True,                         # the filter step by identifier/kernels.py (numba); False: the
                                              # numpy pieces (identifier/pf.py), the reference
}


_K = None   # identifier.kernels once a compiled strategy is built (base.load_kernels)


def per_dimension(triple, n: int) -> np.ndarray:
    """(lambda0, lambda_i, tau_i) -> a (2n+1,) vector; a scalar applies to every dimension."""
    t = np.broadcast_to(np.asarray(triple, float), (3,)) if np.ndim(triple) == 0 else np.asarray(triple, float)
    if t.size == 2 * n + 1:
        return t.copy()
    if t.size != 3:
        raise ValueError(f"expected 3 or {2 * n + 1} numbers, got {t.size}")
    return np.r_[t[0], np.full(n, t[1]), np.full(n, t[2])]


class MdipfStrategy(Strategy):
    name = "mdipf"
    defaults = DEFAULTS
    use_box = False
    # What a variant replaces, declared (the compiled fast paths need the plain pieces; a subclass
    # that overrides one says so here, and tests/test_strategies.py checks every class's word):
    plain_step = True           # _step, _constrain, _move, _log_likelihood and _weigh as here
    plain_constrain = True      # _constrain (and ProposedStrategy's _constrain_in_box) as in the base
    plain_projection = True     # _project as in its base (MDIPF: none; proposed: the clip)
    plain_prelim = True         # preliminary_fit as here
    plain_recentre = True       # _after_recentre as in its base (re-centring may wait for the next step)

    def __init__(self, settings, seed: int = 0):
        super().__init__(settings, seed)
        opts = {**self.defaults, **self.options}
        unknown = set(opts) - set(self.defaults) - {"window_samples", "k_pe", "c_lw", "c_up"}
        if unknown:
            raise ValueError(f"{self.name}: unknown option(s) {', '.join(sorted(unknown))}")
        self.opts = opts
        p = self.theta.size
        n = (p - 1) // 2
        self.n_particles = int(opts["particles"])
        self.init_std = per_dimension(opts["init_std"], n)
        self.transition_std = per_dimension(opts["transition_std"], n)
        self.noise_std = float(opts["noise_std"])
        if self.n_particles < 2:
            raise ValueError(f"{self.name}: particles must be at least 2, got {self.n_particles}")
        for key, value in (("init_std", self.init_std), ("transition_std", self.transition_std)):
            if not np.all(np.isfinite(value) & (value >= 0)):
                raise ValueError(f"{self.name}: {key} must be finite and >= 0, got {opts[key]}")
        if not (math.isfinite(self.noise_std) and self.noise_std > 0):
            raise ValueError(f"{self.name}: noise_std must be finite and > 0, got {opts['noise_std']}")
        self.particles = np.zeros((p, self.n_particles)).T   # (N, P), a view of the (P, N) cloud self._xt
        # scratch buffers of the filter step (P, N) / (n, N): the step allocates almost nothing
        self._spare = np.empty((p, self.n_particles))
        self._d = np.empty((p, self.n_particles))
        self._dw = np.empty((p, self.n_particles))
        self._tmp = np.empty((n, self.n_particles))
        self._arange = np.arange(self.n_particles)
        self.weights = np.full(self.n_particles, 1.0 / self.n_particles)
        # the compiled step's buffers: log-likelihoods, the other weight vector, ancestor indices
        global _K
        _K = load_kernels()
        self._compiled = bool(opts["compiled"]) and _K.AVAILABLE
        if self._compiled:
            _K.warm_up()                     # compile / load now, before the fault, not on the first sample
            self._ll = np.empty(self.n_particles)
            self._w_spare = np.empty(self.n_particles)
            self._idx = np.empty(self.n_particles, np.intp)
        # the whole step in one compiled call (kernels.filter_step) where this class's step is the
        # plain one: Theta row-normalised, no constraint, no projection or the "clip" one
        self._fused = (self._compiled and opts["stabiliser"] == "rownorm" and self.plain_step
                       and self._can_fuse_projection())
        # with the fused step, what a correction does to the cloud (its re-centring, and with a box
        # the box's contraction and the clip into it) waits for the next step, which does it first
        # (``_settle_recentre``; reading ``particles`` does it too): the same operations in the same
        # order, off the sample that closes the window
        self._defer_recentre = self._fused and self.plain_recentre and not opts["reset_cloud"]
        self._shift = np.zeros(p)            # chi^_Q still to subtract from the cloud
        self._recentre_pending = False
        # Random numbers are drawn before the fault, when the TCU is idle: the first block of
        # transition noise (kept transposed and scaled, as the filter step adds it) and the initial
        # cloud, in that order from the one generator (the order the filter would draw them).
        self._noise_block = max(1, int(opts["noise_block"]))
        block = self.rng.standard_normal((self._noise_block, self.n_particles, p))
        self._noise = np.ascontiguousarray(block.transpose(0, 2, 1) * self.transition_std[None, :, None])   # (B, P, N)
        self._noise_next = 0
        # the first cloud, scaled and laid out (P, N) as the filter keeps it
        self._next_cloud = np.ascontiguousarray((self.rng.standard_normal((self.n_particles, p)) * self.init_std).T)
        # ... and the resampling's uniforms for as many steps (the generator's first call after a
        # long idle spell is slow; these follow the cloud, as the first draws did)
        self._uniforms = self.rng.random(self._noise_block).tolist()
        self._uniforms.reverse()             # pop() from the end takes them in the drawn order
        self._next_weights = np.full(self.n_particles, 1.0 / self.n_particles)
        self.base = self.theta.copy()        # theta_{Q-1}: the curve the errors are relative to
        self.prelim_done = False
        self._job = None                     # the prelim's polish in progress (prelim_polish_per_sample)
        self._queue: deque = deque()         # (v, mu) fed during the polish, not yet filtered
        self._steps_taken = 0                # steps made from the queue
        self._prelim_samples = 0             # samples the prelim fitted (window 1)
        # the "grid" prelim's lattice, built over window 1's samples (set up now, before the fault)
        self._grid_acc = None
        if self._spread_prelim() or (self._compiled and opts["filter_prelim_window"] and opts["prelim_solver"] == "grid"
                                     and opts["prelim_radius"] is not None):
            self._grid_acc = GridAccumulator(self.theta, self.prelim_radius(), int(opts["prelim_grid"]),
                                             int(opts["prelim_iterations"]), max(64, self.window_samples),
                                             compiled=self._compiled)
        self.history: list[np.ndarray] = []  # theta after each correction (for plots)

    @property
    def keeps_warm(self) -> bool:
        # compiled steps and the compiled lattice prelim: every sample's work is bounded (the
        # scipy prelims of the *_raw and mu0 variants are not)
        return self._compiled and self.opts["prelim_solver"] == "grid" and self.plain_prelim

    # -- the cloud: kept as a (P, N) C-contiguous array; ``particles`` is its (N, P) view --------
    _recentre_pending = False                # (before __init__ sets it: the setter below runs first)

    @property
    def particles(self) -> np.ndarray:
        if self._recentre_pending:
            self._settle_recentre()
        return self._xt.T

    @particles.setter
    def particles(self, value) -> None:
        self._xt = np.ascontiguousarray(np.asarray(value, dtype=float).T)

    # -- the filter -------------------------------------------------------------------------
    def _draw_cloud(self) -> None:
        if self._next_cloud is not None:     # drawn (and, with a box, clipped) before the fault
            self._xt, self._next_cloud = self._next_cloud, None
            self.weights, self._next_weights = self._next_weights, None
            if self.plain_constrain:
                return                       # finite by construction (finite init_std, checked above)
        else:
            self.particles = self.rng.standard_normal(self.particles.shape) * self.init_std
            self.weights = np.full(self.n_particles, 1.0 / self.n_particles)
        self._constrain()

    def _constrain(self) -> None:
        """Hook for variants that restrict the cloud (e.g. mu(0) = 0); also keeps it finite."""
        if math.isfinite(self._xt.sum()):
            return
        bad = ~np.all(np.isfinite(self._xt), axis=0)
        self._xt[:, bad] = 0.0

    def on_sample(self, creep_speed_kmh: float, mu_hat: float) -> None:
        if not self.prelim_done:
            self._before_filter(creep_speed_kmh, mu_hat)
            return
        if self._queue:                    # still catching up on the samples fed during the prelim's polish
            self._queue.append((creep_speed_kmh, mu_hat))
            # the filter's first step (on cold caches, several times a later one) alone on its sample
            first = self._steps_taken == 0
            self._drain(1 if first else int(self.opts["catch_up_per_sample"]))
            return
        self._step(creep_speed_kmh, mu_hat)

    def _can_fuse_projection(self) -> bool:
        """Whether the compiled step can do this class's projection (none here)."""
        return self.plain_projection

    def _clip_box(self):
        """(lo, hi, use_box): the box the fused step clips the cloud into (MDIPF: none)."""
        return self.base, self.base, False

    def _step(self, creep_speed_kmh: float, mu_hat: float) -> None:
        """One filter step on one sample."""
        if self._recentre_pending:
            self._settle_recentre()
        if self._fused:
            lo, hi, use_box = self._clip_box()
            noise = self._transition_noise()
            ess = _K.filter_step(self._xt, self.weights, noise, self._spare, self._d, self.base, creep_speed_kmh,
                                 mu_hat, -0.5 / self.noise_std ** 2, lo, hi, use_box, self._ll, self._w_spare,
                                 self._tmp)
            if ess == -1.0:                    # no transition from this cloud: the reference path
                self._move(noise)
            else:
                self._spare, self._xt = self._xt, self._spare
            if ess >= 0.0:
                self._w_spare, self.weights = self.weights, self._w_spare
                self._resample_if_low(ess)
            elif ess == -3.0:                  # moved and clipped; the weights in logarithms
                self._weigh(self._ll)
            else:
                self._constrain()
                self._project(creep_speed_kmh, mu_hat)
                self._weigh(self._log_likelihood(creep_speed_kmh, mu_hat))
            return
        self._move()
        self._constrain()
        self._project(creep_speed_kmh, mu_hat)
        self._weigh(self._log_likelihood(creep_speed_kmh, mu_hat))

    def _drain(self, limit: int | None = None) -> None:
        """Ordinary filter steps on the oldest queued samples (all of them when ``limit`` is None)."""
        q = self._queue
        count = len(q) if limit is None else min(len(q), max(1, limit))
        for _ in range(count):
            self._step(*q.popleft())
            self._steps_taken += 1

    # The step below is pf.correlation_transition / propagate / log_likelihood / normalise /
    # resample to the last bit, written on the (P, N) cloud with preallocated buffers and as few
    # numpy calls as possible (per-call overhead, not arithmetic, is most of a step at N = 1000).
    def _move(self, noise: np.ndarray | None = None) -> None:
        """chi(k) = Theta(k-1) chi(k-1) + beta (eq. 12), into the spare buffer (then swapped);
        ``noise``: beta if already drawn."""
        st = self.opts["stabiliser"]
        if noise is None:
            noise = self._transition_noise()
        if st == "rownorm" and self._compiled and _K.rownorm_propagate(self._xt, self.weights, noise, self._spare,
                                                                       self._d):
            self._spare, self._xt = self._xt, self._spare
            return
        if st == "rownorm":
            transition = pf.rownorm_transition(self._xt, self.weights, self._d, self._dw)
        else:
            transition = pf.correlation_transition(self._xt.T, self.weights, st)
        new = np.matmul(transition, self._xt, out=self._spare)
        new += noise
        self._spare, self._xt = self._xt, new

    def _transition_noise(self) -> np.ndarray:
        """beta for this step, (P, N), scaled by B: from the pre-drawn block, then one draw per step
        (no burst of a whole block on one sample)."""
        if self._noise_next < self._noise_block:
            self._noise_next += 1
            return self._noise[self._noise_next - 1]
        return np.ascontiguousarray(self.rng.standard_normal(self._xt.T.shape).T * self.transition_std[:, None])

    def _curve_at(self, creep_speed_kmh: float) -> np.ndarray:
        """M_cor(v_s) per particle (N,), a new array (pf.curve_at to the last bit)."""
        xt, base, tmp = self._xt, self.base, self._tmp
        n = tmp.shape[0]
        with np.errstate(over="ignore", invalid="ignore"):
            np.add(xt[1 + n:], self._base_col[1 + n:], out=tmp)
            tmp *= creep_speed_kmh
            np.exp(tmp, out=tmp)
            out = (xt[1] + base[1]) * tmp[0]
            for i in range(1, n):
                out += (xt[1 + i] + base[1 + i]) * tmp[i]
            out += xt[0] + base[0]
        return out

    def _log_likelihood(self, creep_speed_kmh: float, mu_hat: float) -> np.ndarray:
        """log N(mu^ ; M_cor(v_s), G) per particle; -inf where not finite (pf.log_likelihood)."""
        if self._compiled:
            _K.log_likelihood(self._xt, self.base, creep_speed_kmh, mu_hat, -0.5 / self.noise_std ** 2, self._ll,
                              self._tmp)
            return self._ll
        resid = self._curve_at(creep_speed_kmh)
        np.subtract(mu_hat, resid, out=resid)
        resid *= resid
        resid *= -0.5 / self.noise_std ** 2
        if not math.isfinite(resid.sum()):
            resid[~np.isfinite(resid)] = -np.inf
        return resid

    def _weigh(self, ll: np.ndarray) -> None:
        """w <- w_prev p(Z | chi), normalised; resample (``resampler``) when the ESS is low.

        As w_prev exp(ll - max ll) / sum (one max shift, no logarithms: ``kernels.reweigh``, or
        numpy); when that underflows (every product 0) or is not finite, by log weights
        (pf.normalise), which cannot."""
        ess = self._reweigh(ll)
        if ess is None:
            with np.errstate(divide="ignore"):
                self.weights = pf.normalise(np.log(self.weights) + np.where(np.isnan(ll), -np.inf, ll))
            ess = 1.0 / np.dot(self.weights, self.weights)
        self._resample_if_low(ess)

    def _reweigh(self, ll: np.ndarray) -> float | None:
        """New weights without logarithms (``ll`` left as it is); their ESS, or None if that underflows."""
        if self._compiled:
            ess = _K.reweigh(ll, self.weights, self._w_spare)
            if not ess > 0.0:
                return None
            self._w_spare, self.weights = self.weights, self._w_spare
            return ess
        top = ll.max()
        if not math.isfinite(top):
            return None
        w = np.subtract(ll, top)
        np.exp(w, out=w)
        w *= self.weights
        total = w.sum()
        if not (total > 0.0 and math.isfinite(total)):
            return None
        w /= total
        self.weights = w
        return 1.0 / np.dot(w, w)

    def _resample_if_low(self, ess: float) -> None:
        """Resampling (``resampler``) when ESS < ``ess_fraction`` * N; systematic by counts."""
        o = self.opts
        if ess >= o["ess_fraction"] * self.n_particles:
            return
        if o["resampler"] == "systematic":
            u0 = self._uniforms.pop() if self._uniforms else self.rng.random()
            idx = (_K.systematic_resample(self.weights, u0, self._idx) if self._compiled
                   else pf.systematic_counts_resample(self.weights, u0, self._arange))
        else:
            idx = pf.resample(self.weights, self.rng, o["resampler"])
        self._take(idx)
        self.weights.fill(1.0 / self.n_particles)

    @property
    def _base_col(self) -> np.ndarray:
        return self.base[:, None]

    def _take(self, idx: np.ndarray) -> None:
        """Keep the particles ``idx`` (resampling); variants with per-particle state extend this."""
        if self._compiled:
            _K.take_columns(self._xt, idx, self._spare)
            self._spare, self._xt = self._xt, self._spare
        else:
            self._xt = self._xt.take(idx, axis=1)

    def _project(self, creep_speed_kmh: float, mu_hat: float) -> None:
        """The projection domain (proposed strategy); MDIPF has none."""

    def _after_correction(self, estimate: np.ndarray) -> None:
        """Hook run after chi^_Q is known (the box update of the proposed strategy)."""

    # -- one correction per window -------------------------------------------------------------
    def prelim_radius(self):
        r = self.opts["prelim_radius"]
        return None if r is None else per_dimension(r, (self.theta.size - 1) // 2)

    def preliminary_fit(self, window_v, window_mu) -> np.ndarray:
        solver = self.opts["prelim_solver"]
        if solver == "lm":
            return fit_curve_lm(window_v, window_mu, self.theta, self.prelim_radius(), int(self.opts["prelim_iterations"]))
        if solver == "grid" and self._compiled and self.prelim_radius() is not None:
            # the lattice built sample by sample (as window 1's samples came, when the accumulator
            # was set up before the fault; else now), solved and polished by the compiled kernels
            acc, self._grid_acc = self._grid_acc, None
            if acc is None or acc.count != len(window_v):
                acc = GridAccumulator(self.theta, self.prelim_radius(), int(self.opts["prelim_grid"]),
                                      int(self.opts["prelim_iterations"]), max(len(window_v), 1), compiled=True)
                for v_k, mu_k in zip(np.asarray(window_v, float).tolist(), np.asarray(window_mu, float).tolist()):
                    acc.add(v_k, mu_k)
            job = acc.job(window_v, window_mu)
            while not job.done:
                job.step()
            return job.x
        if solver == "grid":
            return fit_curve_grid(window_v, window_mu, self.theta, self.prelim_radius(), int(self.opts["prelim_grid"]),
                                  int(self.opts["prelim_iterations"]))
        if solver != "trf":
            raise ValueError(f"{self.name}: prelim_solver must be 'trf', 'grid' or 'lm'")
        return fit_curve(window_v, window_mu, self.theta, self.prelim_radius())

    # -- the preliminary fit spread over samples (prelim_polish_per_sample > 0) ---------------------
    def _spread_prelim(self) -> bool:
        o = self.opts
        return (o["prelim_solver"] == "grid" and int(o["prelim_polish_per_sample"]) > 0
                and not o["filter_prelim_window"] and o["prelim_radius"] is not None)

    def _before_filter(self, creep_speed_kmh: float, mu_hat: float) -> None:
        """A sample before the filter runs: window 1 builds the prelim's lattice (when the prelim
        is spread), the samples after it advance the prelim's polish."""
        if self._job is not None:
            self._advance_prelim()
        elif self._grid_acc is not None and self._grid_acc.count < min(self.window_samples, self._grid_acc.size):
            self._accumulate(creep_speed_kmh, mu_hat)

    def _accumulate(self, creep_speed_kmh: float, mu_hat: float) -> None:
        """A window-1 sample into the prelim's lattice (nlls.GridAccumulator)."""
        self._grid_acc.add(creep_speed_kmh, mu_hat)

    def _start_prelim_job(self, window_v, window_mu):
        """The "grid" prelim's lattice solved now (its sums were built sample by sample); its LM
        polish as a job for the next samples."""
        acc, self._grid_acc = self._grid_acc, None
        if acc is None or acc.count != len(window_v):
            return fit_curve_grid(window_v, window_mu, self.theta, self.prelim_radius(), int(self.opts["prelim_grid"]),
                                  int(self.opts["prelim_iterations"]), job=True)
        return acc.job(window_v, window_mu)

    def _advance_prelim(self) -> None:
        """Called by on_sample while the prelim is pending: at most ``prelim_polish_per_sample``
        polish iterations per sample; on the first sample after the polish ended, the filter
        starts and catches up on the samples that arrived meanwhile (``_catch_up``)."""
        job = self._job
        if not job.done:
            for _ in range(int(self.opts["prelim_polish_per_sample"])):
                if job.step():
                    break
            return
        # compiled: the polish was one call on the previous sample; the filter opens on this one and
        # its first step waits for the next (each of the three is costly on cold caches)
        self._finish_prelim(now=False, catch_up=0 if self._compiled else None)

    def _finish_prelim(self, now: bool = True, catch_up: int | None = None) -> None:
        """The prelim is final: open the filter (cloud drawn around it, the prelim's correction
        event on this sample) and queue the samples fed since window 1 ended; the filter steps
        through them in order, ``catch_up`` (default ``catch_up_at_open``) on this sample and
        ``catch_up_per_sample`` per later sample (all at once with ``now``), so it computes exactly
        the steps it would have made on time, only later (a window's correction first finishes the queue)."""
        job, self._job = self._job, None
        while not job.done:
            job.step()
        self._begin_filter(job.x)
        self._queue.extend(zip(self._v[self._window_start:], self._mu[self._window_start:]))
        catch_up = int(self.opts["catch_up_at_open"]) if catch_up is None else catch_up
        if now:
            self._drain()
        elif catch_up > 0:
            self._drain(catch_up)

    def _curve_many(self, v: np.ndarray) -> np.ndarray:
        """M_cor at several creep speeds per particle: (N, S) (curve.mu_model on the (P, N) cloud)."""
        xt, base = self._xt, self.base
        n = (xt.shape[0] - 1) // 2
        with np.errstate(over="ignore", invalid="ignore"):
            e = np.exp((xt[1 + n:] + base[1 + n:, None])[:, :, None] * v)         # (n, N, S)
            e *= (xt[1:1 + n] + base[1:1 + n, None])[:, :, None]
            m = e.sum(axis=0)
            m += (xt[0] + base[0])[:, None]
        return m

    def correction_ready(self) -> bool:
        return self.prelim_done

    def correct_pending(self):
        if not self.prelim_done:           # a window closed first: finish now
            self._finish_prelim(now=True)
        estimate = np.zeros_like(self.base)
        self._estimate_for_theta = estimate
        return estimate if self.opts["j_ef_from_prelim"] else np.full_like(self.base, np.nan)

    def _begin_filter(self, theta_pre) -> None:
        self.base = np.asarray(theta_pre, float)
        if not math.isfinite(float(self.base.sum())):
            self.base = self.theta.copy()
        self.prelim_done = True
        self._draw_cloud()
        self._after_prelim()

    def correct(self, window_v, window_mu):
        if self._queue:                    # a window closed before the filter caught up: catch up now
            self._drain()
        if not self.prelim_done:
            self._prelim_samples = len(window_v)
        if not self.prelim_done and self._spread_prelim():
            self._job = self._start_prelim_job(window_v, window_mu)
            if not self._job.done:
                return None
            self._finish_prelim(now=True)         # (no polish to spread: prelim_iterations = 0)
            estimate = np.zeros_like(self.base)
            self._estimate_for_theta = estimate
            return estimate if self.opts["j_ef_from_prelim"] else np.full_like(self.base, np.nan)
        if not self.prelim_done:
            self._begin_filter(self.preliminary_fit(window_v, window_mu))
            estimate = np.zeros_like(self.base)            # chi^_0: the prelim corrects nothing
            if self.opts["filter_prelim_window"]:
                # correction 1 on the same window: J_EF(1) = |chi^_1 - chi^_0|^2 is known one window early
                for v_k, mu_k in zip(window_v, window_mu):
                    self.on_sample(float(v_k), float(mu_k))
                estimate = self.weights @ self.particles
                if not math.isfinite(float(estimate.sum())):
                    estimate = np.zeros_like(self.base)
                self._last_estimate = np.zeros_like(self.base)
                self._estimate_for_theta = estimate
                return estimate
            self._estimate_for_theta = estimate
            return estimate if self.opts["j_ef_from_prelim"] else np.full_like(self.base, np.nan)
        if self._recentre_pending:
            self._settle_recentre()
        estimate = self._posterior_mean()
        if not math.isfinite(float(estimate.sum())):
            estimate = np.zeros_like(self.base)
        self._estimate_for_theta = estimate
        return estimate

    def peak_intervals(self, level: float):
        """From the weighted cloud: every particle's curve (the base its errors are relative to, plus
        its error vector), its peak in closed form, weighted quantiles (a credible interval of the
        filter's posterior; NaN before the filter opens or for other than two-term curves)."""
        if not self.prelim_done or self._xt.shape[0] != 5:
            return super().peak_intervals(level)
        base = self.base - self._shift if self._recentre_pending else self.base
        if not self._compiled:
            return cloud_peak_intervals(self._xt.T + base, self.weights, level)
        v, mu = np.empty(self.n_particles), np.empty(self.n_particles)
        _K.cloud_peaks(self._xt, base, v, mu)                        # the same peaks, one compiled pass
        ok = np.isfinite(v)
        if not ok.any():
            return super().peak_intervals(level)
        qs = np.array([0.5 * (1.0 - level), 0.5 * (1.0 + level)])
        w = self.weights[ok]
        out = []
        for x in (mu[ok], v[ok]):
            q = np.empty(2)
            _K.weighted_quantiles_hist(x, w, qs, 2048, np.empty(2048), q)
            out.append((float(q[0]), float(q[1])))
        return out[0], out[1]

    def _posterior_mean(self) -> np.ndarray:
        """chi^ = sum_j w_j chi_j (eq. 21), a new (P,) array."""
        if self._compiled:
            return _K.weighted_mean(self._xt, self.weights, np.empty(self._xt.shape[0]))
        return self.weights @ self.particles

    def published_curve(self, candidate):
        """``publish_latest``: the candidate plus the filter's estimate over the confirmation window
        (its samples were filtered before the check ran), i.e. one more correction at no extra time;
        else the candidate, as the paper."""
        if not self.opts["publish_latest"] or not self.prelim_done:
            return candidate
        if self._queue:
            self._drain()
        if self._recentre_pending:
            self._settle_recentre()
        latest = self.base + self._posterior_mean()
        return latest if math.isfinite(float(latest.sum())) else candidate

    def _after_prelim(self) -> None:
        """Hook: the proposed strategy opens its box here."""

    def _recentre_changes(self, chi: np.ndarray) -> bool:
        """Whether re-centring by ``chi`` changes the cloud (MDIPF: only a non-zero shift does)."""
        return bool(chi.any())

    def estimate_to_theta(self, estimate):
        # ``estimate`` may be the NaN placeholder of the prelim (j_ef_from_prelim False): use ours
        chi = self._estimate_for_theta
        theta = self.base + chi
        if not math.isfinite(float(theta.sum())):
            theta = self.base.copy()
        if self._recentre_pending:                          # the previous correction's, never stepped on
            self._settle_recentre()
        if self._defer_recentre:                            # done by the next step (_settle_recentre)
            self._shift[:] = chi
            self._recentre_pending = True
        else:
            self._after_correction(chi)
            if self.opts["reset_cloud"]:
                self._draw_cloud()
            elif chi.any():                                 # (the prelim's chi^_0 = 0 moves nothing)
                self._xt -= chi[:, None]                    # errors now relative to the new theta
            self._after_recentre()
        self.base = theta.copy()
        self.history.append(theta.copy())
        return theta

    def _after_recentre(self) -> None:
        """Hook: the proposed strategy puts the re-centred cloud back into its new box."""

    def _settle_recentre(self) -> None:
        """The deferred part of the last correction (``_defer_recentre``): ``_after_correction``, then
        chi <- chi - chi^_Q and the clip into the (new) box in one compiled pass (``kernels.recentre``,
        which is the plain ``_after_recentre``); skipped when neither moves."""
        self._recentre_pending = False
        chi = self._shift
        self._after_correction(chi)
        if self._recentre_changes(chi):
            lo, hi, use_box = self._clip_box()
            _K.recentre(self._xt, chi, lo, hi, use_box)
        chi.fill(0.0)
