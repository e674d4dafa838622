"""``bayes``: the posterior over the fault curve from every reading since the slip began, with
intervals, confirming only what the data support (beyond the paper; in the exponential form: on
curves of another form it can confirm a wrong peak, which the form-free ``gp`` does not).

Model (particle j carries one curve phi_j of the prior, identifier/prior.py, and a speed estimate):

    omega(k+1) = omega(k) + (dt / J) (T_e(k) - c mbar_j(k)) + w(k),   w ~ N(0, q)     the wheelset (eq. A)
    mbar_j(k)  = (M_j(v_s(k)) + M_j(v_s(k+1))) / 2                                     trapezoid over the period
    y(k)       = omega(k) + n(k),                                     n ~ N(0, sigma_y^2)  the motor-speed sensor

with J the equivalent inertia, c the torque per unit mu, T_e the TCU's own command and v_s the creep
from the measured motor speed and the train speed smoothed by a straight-line fit.  For each particle
a scalar Kalman filter gives the exact Gaussian likelihood of the motor-speed readings (the prediction
error e_j with variance S shared by all particles):

    omega^-_j = omega^_j + (dt / J) (T_e - c mbar_j)          P- = P + q          predict
    e_j = y - omega^-_j,   S = P- + sigma_y^2                                      innovation
    log w_j += -e_j^2 / (2 S)                                                      weigh
    K = P- / S,   omega^_j = omega^-_j + K e_j,   P = (1 - K) P-                   update

So the load-torque observer's transient needs no settle time and no lag pairing: the model is of the
speed itself (``observer_aware``: every sample from the detected slip start on).  sigma_y is
measured before the fault from second differences of the motor speed (Var(y(k+1) - 2 y(k) + y(k-1))
= 6 sigma_y^2 for a smooth speed), so the likelihood's scale is the sensor's, not a tuning knob; q
covers the creep's own noise in M (its slope times the creep noise) and ``model_mu_std`` of model
error, both in mu units.

When the effective sample size falls below ``ess_fraction`` N the cloud is resampled (systematic) and
every particle takes ``moves`` Metropolis steps in the prior's unconstrained coordinates u
(identifier/prior.py; resample-move, Gilks and Berzuini 2001): u' = u + L eps, L L^T = Cov(u) 2.38^2 / 5,
each proposal's filter run afresh over every sample so far (``kernels.bayes_move``), accepted with
min(1, L(u') p(u') / (L(u) p(u))).  This leaves the posterior exact in distribution; a Liu-West
kernel (a Gaussian shrink-and-jitter, no likelihood) drifts off the posterior's curved ridge between
peak mu and peak creep over the many moves of a slow slip and confirms curves whose likelihood is
far below the truth's.  The price is the rerun, O(N x samples) per step of every particle, so the
move is spread over the samples that follow the resampling: each sample advances it by about
``move_budget`` particle-samples (0: all in the resampling's sample).  A Metropolis step that leaves
the posterior of all samples so far invariant keeps a weighted particle properly weighted, so a
particle moved some samples after the resampling, weighted since, is still a draw of the posterior.
While a move is under way the cloud is not resampled again and does not confirm (it holds copies);
it confirms only with an effective sample size of at least ``confirm_min_ess`` N.  The first
``min_samples`` samples (they arrive together at the slip's detection) and a sample that publishes
a correction neither resample nor move.  The bench (``hil bench identify``, docs/design/identification.md)
measures what the budget trades: per-sample cost against the intervals' coverage and RT.

Intervals: weighted quantiles of peak_mu and peak_creep_kmh over the cloud, a credible interval.
Every ``report_samples`` samples a correction event publishes the posterior's curve (weighted
medians of peak mu and peak creep, weighted means of the rest in u) with its 90 % intervals.
Confirmation: at every sample, when (1) the interval at ``confirm_level`` (98 %) lies where the
estimate (the weighted median) would be judged correct, i.e. within ``tol_peak_mu`` (3 %) for peak mu
and ``tol_peak_creep`` (10 %) for peak creep (``within_tolerance``); (2) it keeps that tolerance away
from the prior box's edges (a posterior piled against an edge says the truth lies outside what the
prior can represent, not that it is known); (3) the fit holds: the normalised innovations squared,
averaged with the weights over the last ``fit_window`` samples, stay below ``fit_nis_max`` (a law of
another form than the prior's, fitted by its nearest exponential curve, leaves structured residuals
that a narrow interval alone would hide).  It does not catch every such law: the design note
``docs/design/identification.md`` gives the bench's wrong confirmations, all on Polach curves.  The event
carries the curve and its 90 % intervals.  When the creep passes the prior's highest peak creep
(the TCU then knows the serious stage has begun without having pinned the curve) or after
``max_samples``, an ``unconfirmed`` event reports the best estimate and its intervals instead.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from ..messages import IdentificationEvent
from ..prior import NAMES, CurvePrior, theta_from_phi, theta_from_phi_floats
from ..pf import weighted_quantiles
from ..speed_likelihood import SpeedFilter
from .base import Sample, load_kernels
from .speed_model import BaselineStats, SpeedModelStrategy, within_tolerance  # noqa: F401 (BaselineStats: tests)
#: bins of the compiled quantiles' histogram (kernels.weighted_quantiles_hist): its error is below
#: (max - min) / QUANTILE_BINS, e.g. 0.0013 km/h of peak creep over the default prior
QUANTILE_BINS = 2048
#: the steepest dmu/dv_s the creep noise is taken through into the process noise (1 per km/h: above
#: what the prior's curves reach where the samples are, ~0.3 at zero creep for FFCC-a)
MAX_SLOPE_PER_KMH = 1.0
#: what a moved particle costs besides its rerun (its proposal, curve and acceptance), in samples of a
#: rerun: 50-100 ns against ~2.8-3.7 ns a particle-sample (kernels.bayes_move at N = 1000-2000)
MOVE_OVERHEAD_SAMPLES = 30

DEFAULTS = {
    "particles": 2000,
    **{name: None for name in NAMES},    # prior box sides, e.g. peak_mu = [0.05, 0.25]; None: prior.DEFAULT_BOX
    "confirm_level": 0.98,               # the interval that must be within tolerance to confirm
    "report_level": 0.90,                # the interval published with every event
    "tol_peak_mu": 0.03,                 # half-width / centre allowed at confirmation
    "tol_peak_creep": 0.10,
    "model_mu_std": 3e-4,                # model error per period, mu units (process noise q)
    "discrepancy_mu_std": 0.0,           # the random walk of the mu offset per period (speed_likelihood)
    "ess_fraction": 0.5,
    "confirm_min_ess": 0.1,              # the least effective sample size (fraction of N) that confirms
    "moves": 2,                          # Metropolis steps per particle after each resampling
    "move_budget": 100000,               # the moves' work per sample, in particle-samples (0: all at once)
    "report_samples": 5,                 # a correction event every this many samples
    "min_samples": 5,                    # no confirmation before this many
    "max_samples": 400,
    "fit_window": 20,                    # samples of the fit check (fit_ok)
    "fit_nis_max": 2.0,                  # the largest mean normalised innovation squared that confirms
    "baseline_readings": 400,            # readings before the slip used for sigma_y and the train speed fit
    "sigma_y_fallback": 0.005,           # rad/s, when there is no baseline (samples fed without readings)
    "normals_drawn_ahead": 16,           # proposal draws made at construction (reused cyclically)
    "compiled": True,                    # the cloud's passes by identifier/kernels.py (numba); False: numpy
}


def _log_prior_u(u: np.ndarray) -> np.ndarray:
    """log p(u) of the prior in its unconstrained coordinates, per particle (u: (5, N)): each coordinate
    is the logit of a uniform, so log p = sum log(s (1 - s)) with s = sigmoid(u)."""
    return -np.sum(np.abs(u) + 2.0 * np.log1p(np.exp(-np.abs(u))), axis=0)


class BayesStrategy(SpeedModelStrategy):
    """Particle posterior over the prior's curves with a Kalman likelihood of the motor speed
    (module docstring).  ``compiled`` (default) runs the cloud's step, move and intervals by
    ``identifier/kernels.py``; False runs the numpy reference (``speed_likelihood``, ``prior``)."""

    name = "bayes"
    defaults = DEFAULTS

    def __init__(self, settings, seed: int = 0):
        super().__init__(settings, seed)
        o = self.opts = self.merged_options()
        self.prior = CurvePrior.from_options({k: v for k, v in o.items() if k in NAMES and v is not None})
        self.n_particles = n = int(o["particles"])
        if not 10 <= n <= 1_000_000:
            raise ValueError(f"{self.name}: particles must be in [10, 1000000], got {o['particles']}")
        for key in ("confirm_level", "report_level"):
            if not 0.5 < float(o[key]) < 1.0:
                raise ValueError(f"{self.name}: {key} must be in (0.5, 1), got {o[key]}")
        for key in ("tol_peak_mu", "tol_peak_creep", "model_mu_std"):
            if not float(o[key]) > 0:
                raise ValueError(f"{self.name}: {key} must be > 0, got {o[key]}")
        if not float(o["discrepancy_mu_std"]) >= 0:
            raise ValueError(f"{self.name}: discrepancy_mu_std must be >= 0, got {o['discrepancy_mu_std']}")
        veh = settings.vehicle
        self.filter = SpeedFilter(settings.period_s, veh.equivalent_inertia_kgm2, veh.torque_per_mu_nm, math.nan,
                                  math.nan)
        self._compiled = bool(o.get("compiled", True)) and load_kernels().AVAILABLE
        if self._compiled:
            load_kernels().warm_up()
        # the cloud, a row per coordinate: u (unconstrained prior coordinates), phi, theta; weights
        self.u = np.ascontiguousarray(self.prior.sample_u(n, self.rng).T)
        self.phi = np.empty((len(NAMES), n))
        self._theta = np.empty((5, n))
        self._bounds = self.prior.bounds()
        self._qs = np.empty(5)
        self._q_out = np.empty(5)
        self._counts = np.empty(QUANTILE_BINS)
        self._set_curves()
        self.log_w = np.zeros(n)
        self.weights = np.full(n, 1.0 / n)
        # the moves' normal numbers, drawn now (before the fault, when the TCU is idle); reused cyclically
        self._normals = self.rng.standard_normal((int(o["normals_drawn_ahead"]), len(NAMES), n))
        self._idx = np.empty(n, np.intp)
        self.ll = np.zeros(n)                  # every particle's whole log-likelihood (its current curve)
        self._log = np.full((7, 256), np.nan)  # per sample: creep, y, torque, dt/J, gain, 1/(2S), offset gain (``_record``)
        self._count = 0
        self.accepted = 0
        self.baseline = BaselineStats(int(o["baseline_readings"]))
        self.omega = None                      # per-particle speed estimate (after the first sample)
        self._step_out = np.empty(2)
        self._nis_recent: deque[float] = deque(maxlen=int(o["fit_window"]))
        self._m_prev: np.ndarray | None = None
        self.resamples = 0
        self._pending = None                   # the move under way after a resampling (``_move``)
        self.ess = float(n)
        # the cloud's gather buffers, by attribute (``_resample``), made and touched now, not on a sample
        self._spare = {name: np.zeros_like(getattr(self, name)) for name in ("u", "phi", "_theta")}
        self.peak_mu_ci = self.peak_creep_ci = (math.nan, math.nan)

    # -- the cloud -----------------------------------------------------------------------------
    def _set_curves(self) -> None:
        """phi and theta of every particle from u."""
        if self._compiled:
            load_kernels().bayes_curves(self.u, *self._bounds, self.phi, *self._theta)
        else:
            self.phi[:] = self.prior.phi_from_u(self.u.T).T
            self._theta[:] = theta_from_phi(self.phi.T).T

    def _mu_at(self, creep_speed_kmh: float) -> np.ndarray:
        """M_j(v_s) for every particle j."""
        if self._compiled:
            out = np.empty(self.n_particles)
            load_kernels().bayes_mu_at(*self._theta, creep_speed_kmh, out)
            return out
        l0, l1, l2, t1, t2 = self._theta
        return l0 + l1 * np.exp(t1 * creep_speed_kmh) + l2 * np.exp(t2 * creep_speed_kmh)

    # -- samples (the loop: speed_model.SpeedModelStrategy) -------------------------------------------
    def _open(self, s: Sample) -> None:
        """The first sample of the slip: the baseline is final; every particle starts at y."""
        f = self.filter
        f.sigma_y_rad_s = self.open_baseline(s, self.opts["sigma_y_fallback"])
        # q: model error plus the creep noise carried into M (a slope of MAX_SLOPE_PER_KMH x the creep noise)
        creep_noise_kmh = self.creep_per_motor_speed * f.sigma_y_rad_s
        mu_std = math.hypot(float(self.opts["model_mu_std"]), MAX_SLOPE_PER_KMH * creep_noise_kmh / math.sqrt(2.0))
        f.q_var = (self.period_s * f.torque_per_mu_nm / f.inertia_kgm2 * mu_std) ** 2
        self.omega = f.open(s.motor_speed_rad_s, self.n_particles)
        self.delta = np.zeros(self.n_particles)            # every particle's mu offset (speed_likelihood)
        f.q_delta_var = float(self.opts["discrepancy_mu_std"]) ** 2
        creep = self.creep_for_likelihood(s)
        self._m_prev = self._mu_at(creep)
        self._record(creep, s, math.nan, math.nan, math.nan, math.nan)

    def _record(self, creep: float, s: Sample, dt_j: float, gain: float, inv_2s: float, gain_delta: float) -> None:
        """What a move needs to run a particle's filter afresh: this sample and the step's constants."""
        k = self._count
        if k == self._log.shape[1]:
            self._log = np.hstack([self._log, np.full_like(self._log, np.nan)])
        self._log[:, k] = (creep, s.motor_speed_rad_s, s.torque_nm, dt_j, gain, inv_2s, gain_delta)
        self._count = k + 1

    def _step(self, s: Sample) -> None:
        """One period of every particle's speed filter (speed_likelihood), then resample-move if needed."""
        prev, f = self._prev, self.filter
        periods = max(s.step - prev.step, 1)
        creep = self.creep_for_likelihood(s)
        dt_j, innov_var, gain, gain_delta = f.gains(periods)
        if self._compiled:
            load_kernels().bayes_step(*self._theta, self.omega, self.delta, self._m_prev, self.log_w, self.ll,
                                      self.weights, creep, s.motor_speed_rad_s, prev.torque_nm, dt_j,
                                      f.torque_per_mu_nm, 0.5 / innov_var, gain, gain_delta, self._step_out)
            ess, nis = self._step_out
        else:
            m_new = self._mu_at(creep)
            mbar = 0.5 * (self._m_prev + m_new) + self.delta
            pred = self.omega + dt_j * (prev.torque_nm - f.torque_per_mu_nm * mbar)
            e = s.motor_speed_rad_s - pred                             # the SpeedFilter step, its gains as above
            self.omega = pred + gain * e
            self.delta = self.delta + gain_delta * e
            ll = -0.5 / innov_var * e * e
            nis = -2.0 * float(self.weights @ ll)
            self.log_w += ll
            self.ll += ll
            self._m_prev = m_new
            w = np.exp(self.log_w - self.log_w.max())
            self.weights = w / w.sum()
            ess = 1.0 / float(self.weights @ self.weights)
        self._record(creep, s, dt_j, gain, 0.5 / innov_var, gain_delta)
        self.ess = float(ess)
        # the fit's check: the recent normalised innovations squared (about 1 when a curve of the prior
        # explains the speed; well above when none does, e.g. a law of another form)
        self._nis_recent.append(float(nis))
        # a sample that publishes a correction neither resamples nor moves (its cost is the summary's),
        # nor do the first min_samples (they arrive together when the slip is detected: the catch-up)
        publishes = len(self._v) % int(self.opts["report_samples"]) == 0
        if self._pending is not None:
            if not publishes:
                self._move(int(self.opts["move_budget"]))
        elif (ess < float(self.opts["ess_fraction"]) * self.n_particles and not publishes
              and len(self._v) >= int(self.opts["min_samples"])):
            self._resample()
            if int(self.opts["move_budget"]) <= 0:
                self._move(0)

    def _rerun(self, theta: np.ndarray):
        """(log-likelihood, speed estimate, offset, M at the last sample) of every particle of ``theta``
        (5, N) over all samples so far, afresh."""
        creep, y, torque, dt_j, gain, inv_2s, gain_delta = (np.ascontiguousarray(r[:self._count]) for r in self._log)
        n = theta.shape[1]
        if self._compiled:
            ll, omega, delta, m_last = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
            load_kernels().bayes_rerun(*theta, creep, y, torque, dt_j, gain, inv_2s, gain_delta,
                                       self.filter.torque_per_mu_nm, ll, omega, delta, m_last)
            return ll, omega, delta, m_last
        l0, l1, l2, t1, t2 = (row[:, None] for row in theta)
        m = l0 + l1 * np.exp(t1 * creep) + l2 * np.exp(t2 * creep)                  # (N, S)
        omega, delta, ll = np.full(n, y[0]), np.zeros(n), np.zeros(n)
        c = self.filter.torque_per_mu_nm
        for k in range(1, creep.size):
            pred = omega + dt_j[k] * (torque[k - 1] - c * (0.5 * (m[:, k - 1] + m[:, k]) + delta))
            e = y[k] - pred
            omega = pred + gain[k] * e
            delta = delta + gain_delta[k] * e
            ll -= inv_2s[k] * e * e
        return ll, omega, delta, m[:, -1].copy()

    def _resample(self) -> None:
        """Systematic resampling; the weights become equal and a move is set under way (``_move``):
        ``moves`` Metropolis rounds over the cloud, a Gaussian random walk in u with the resampled
        cloud's covariance x 2.38^2 / 5."""
        n = self.n_particles
        if self._compiled:
            kern = load_kernels()
            cov = kern.weighted_covariance5(self.u, self.weights, np.empty((5, 5)))
            idx = kern.systematic_resample(self.weights, float(self.rng.random()), self._idx)
            for name in ("u", "phi", "_theta"):        # the cloud's rows gathered into the spare buffer
                spare = self._spare[name]
                kern.take_columns(getattr(self, name), idx, spare)
                self._spare[name] = getattr(self, name)
                setattr(self, name, spare)
        else:
            centred = self.u - (self.u @ self.weights)[:, None]
            cov = (centred * self.weights) @ centred.T
            idx = np.minimum(np.searchsorted(np.cumsum(self.weights), (self.rng.random() + np.arange(n)) / n), n - 1)
            self.u, self.phi, self._theta = self.u[:, idx], self.phi[:, idx], self._theta[:, idx]
        self.ll = self.ll[idx]
        self.omega = self.omega[idx]
        self.delta = self.delta[idx]
        self._m_prev = self._m_prev[idx]
        cov *= 2.38 ** 2 / self.u.shape[0]           # the random walk's covariance: the cloud's, weighted
        cov += (1e-12 + 1e-9 * np.trace(cov)) * np.eye(len(cov))
        chol = load_kernels().cholesky_lower(cov, np.empty_like(cov)) if self._compiled else np.linalg.cholesky(cov)
        self._pending = [0, 0, chol, self.rng.random(n)]       # round, next particle, L, uniforms
        self.log_w.fill(0.0)
        self.weights.fill(1.0 / n)
        self.resamples += 1

    def _move(self, budget: int) -> None:
        """Advance the move under way by about ``budget`` particle-samples of filter reruns (0: finish
        it now).  A Metropolis step targets the posterior of all samples so far, so a particle moved
        samples after the resampling, with its weight since, is still a draw of it (a weighted
        particle stays properly weighted under a posterior-invariant kernel): the move's work is
        spread over the samples that follow instead of stalling one of them."""
        n, count = self.n_particles, self._count
        rounds = int(self.opts["moves"])
        while self._pending is not None:
            rnd, start, chol, uniforms = self._pending
            stop = n if budget <= 0 else min(n, start + max(1, budget // (count + MOVE_OVERHEAD_SAMPLES)))
            normals = self._normals[(self.resamples * rounds + rnd) % len(self._normals)]
            self.accepted += self._move_range(start, stop, chol, normals, uniforms)
            if stop < n:
                self._pending[1] = stop
            elif rnd + 1 < rounds:
                self._pending = [rnd + 1, 0, chol, self.rng.random(n)]
            else:
                self._pending = None
            if budget > 0:
                budget -= (stop - start) * (count + MOVE_OVERHEAD_SAMPLES)
                if budget <= 0:
                    return

    def _move_range(self, start: int, stop: int, chol, normals, uniforms) -> int:
        """One Metropolis step for particles [start, stop) (module docstring): the proposal's filter
        over every sample so far, accepted with min(1, L(u') p(u') / (L(u) p(u))).  Returns the
        number accepted."""
        if self._compiled:
            return load_kernels().bayes_move(
                self.u, self.phi, *self._theta, self.omega, self.delta, self._m_prev, self.ll, start, stop, chol, normals,
                uniforms, *self._bounds, *(np.ascontiguousarray(r[:self._count]) for r in self._log),
                self.filter.torque_per_mu_nm)
        sl = slice(start, stop)
        prop = self.u[:, sl] + chol @ normals[:, sl]
        phi_p = self.prior.phi_from_u(prop.T).T
        theta_p = theta_from_phi(phi_p.T).T
        ll_p, omega_p, delta_p, m_p = self._rerun(theta_p)
        accept = np.log(uniforms[sl]) < ll_p - self.ll[sl] + _log_prior_u(prop) - _log_prior_u(self.u[:, sl])
        cols = np.flatnonzero(accept) + start
        self.u[:, cols], self.phi[:, cols], self._theta[:, cols] = prop[:, accept], phi_p[:, accept], theta_p[:, accept]
        self.ll[cols], self.omega[cols], self.delta[cols], self._m_prev[cols] = (ll_p[accept], omega_p[accept],
                                                                                 delta_p[accept], m_p[accept])
        return int(accept.sum())

    # -- intervals and decisions -----------------------------------------------------------------
    def quantiles(self, col: int, qs) -> np.ndarray:
        """Weighted quantiles ``qs`` (ascending) of phi's coordinate ``col`` over the cloud."""
        if not self._compiled:
            return weighted_quantiles(self.phi[col], self.weights, qs)
        k = len(qs)
        self._qs[:k] = qs
        load_kernels().weighted_quantiles_hist(self.phi[col], self.weights, self._qs[:k], QUANTILE_BINS, self._counts,
                                           self._q_out[:k])
        return self._q_out[:k].copy()

    def summary(self, level: float) -> tuple[np.ndarray, tuple[float, float], tuple[float, float]]:
        """The posterior's curve (weighted medians of peak mu and peak creep, the rest from the
        weighted mean in u) and the central intervals at ``level``: one quantile pass per coordinate."""
        qs = (0.5 * (1.0 - level), 0.5, 0.5 * (1.0 + level))
        mu, creep = self.quantiles(0, qs), self.quantiles(1, qs)
        u_mean = load_kernels().weighted_mean(self.u, self.weights, np.empty(len(NAMES))) if self._compiled \
            else self.u @ self.weights
        phi = self.prior.phi_from_u_floats(u_mean)
        phi[0], phi[1] = float(mu[1]), float(creep[1])
        theta = np.array(theta_from_phi_floats(phi))
        return theta, (float(mu[0]), float(mu[2])), (float(creep[0]), float(creep[2]))

    def estimate(self) -> np.ndarray:
        """The posterior's curve (``summary``)."""
        return self.summary(0.9)[0]

    def _spread_within(self, col: int, tol: float) -> bool:
        """Cheap pre-check: the weighted standard deviation within ``tol`` of the mean (a cloud spread
        wider than that cannot have a central 98 % interval of half-width tol x centre)."""
        if self._compiled:
            mean, var = load_kernels().weighted_moments(self.phi[col], self.weights)
        else:
            x = self.phi[col]
            mean = float(self.weights @ x)
            var = float(self.weights @ (x - mean) ** 2)
        return var <= (tol * mean) ** 2

    def fit_ok(self) -> bool:
        """The recent normalised innovations squared, averaged over ``fit_window`` samples, at most
        ``fit_nis_max``: some curve of the prior explains the speed as well as the noise allows."""
        recent = self._nis_recent
        return len(recent) == recent.maxlen and sum(recent) / len(recent) <= float(self.opts["fit_nis_max"])

    def _cloud_ready(self) -> bool:
        """A cloud fit to confirm from: no move under way (a resampled cloud holds copies until its
        move is done) and an effective sample size of at least ``ess_fraction`` N (quantiles of a few
        heavy particles are too narrow)."""
        return self._pending is None and self.ess >= float(self.opts["confirm_min_ess"]) * self.n_particles

    def _within_tolerance(self) -> bool:
        """The confirmation rule (module docstring)."""
        o = self.opts
        tols = (float(o["tol_peak_mu"]), float(o["tol_peak_creep"]))
        if not all(self._spread_within(col, tol) for col, tol in enumerate(tols)):
            return False
        level = float(o["confirm_level"])
        qs = (0.5 * (1.0 - level), 0.5, 0.5 * (1.0 + level))
        for col, (tol, name) in enumerate(zip(tols, NAMES)):
            lo, mid, hi = self.quantiles(col, qs)
            if not within_tolerance(lo, mid, hi, tol):
                return False
            box_lo, box_hi = self.prior.box[name]
            if hi >= box_hi - tol * box_hi or lo <= box_lo + tol * box_lo:
                return False        # piled against the prior's edge: the data point outside what it can say
        return self.fit_ok()

    def _evaluate(self, s: Sample) -> list[IdentificationEvent]:
        n = len(self._v)
        o = self.opts
        if n >= int(o["min_samples"]) and self._cloud_ready() and self._within_tolerance():
            return [self._publish(s, "confirmed")]
        if s.creep_speed_kmh > self.prior.upper_peak_creep_kmh() or n >= int(o["max_samples"]):
            return [self._publish(s, "unconfirmed")]
        if n % int(o["report_samples"]) == 0:
            return [self._publish(s, "correction")]
        return []

    def _publish(self, s: Sample, kind: str) -> IdentificationEvent:
        return self.event(s, kind, *self.summary(float(self.opts["report_level"])))
