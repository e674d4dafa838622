"""A predictive estimate of the current rail's peak, every period, with an online change-point test.

Beside the strategy's confirmation (which waits for a drop's fall past the peak), the TCU keeps, from every
observer sample (creep v_s paired with mu^ as the strategy's are, the rising branch included), a posterior of
the current rail's peak mu ``mu_p`` and peak creep ``v_p``, and publishes each period its 90 % intervals and
centres (``PeakEstimate``).  The closed-loop law acts on it (identifier/control/laws.py ``Identified``).

**The curve model.**  mu(v) = mu_p h_k(|v| / v_p) with the one-parameter shape

    h_k(x) = (1 + k) x / (k + x^(1 + k)),     h_k(1) = 1,  h_k'(1) = 0,  h_k(x) ~ (1 + k) x / k near 0

(k small: a flat tail past the peak and a steep start; k large: a steep fall).  (v_p, k) lie on a grid
(``PEAK_CREEP_GRID_KMH``, 0.08-10 km/h log-spaced: wider than any rail family here, so a rail peaking at
0.2 or at 4 km/h is learnable; ``SHAPES``) with a uniform prior (log-uniform in v_p); mu_p given (v_p, k)
has a conjugate normal prior N(``prior_mu``, ``prior_mu_sd``^2) (a prior, never a bound).  For each cell
the posterior of mu_p is normal and its marginal likelihood is the product of the one-step predictive
densities (the observation model: mu^ = mu_p h + e, e ~ N(0, s^2)):

    prec += h^2 / s^2,   b += h mu^ / s^2,   mean = b / prec
    log p(mu^ | cell, past) = log N(mu^; mean h, s^2 + h^2 / prec)

s is the observer's noise ``noise_mu`` inflated by ``correlation`` (mu^ is a filtered signal: successive
samples are not independent, so each counts as 1 / ``correlation`` of one; the value is chosen for the
intervals' coverage, docs/design/control.md).

**The samples and the memory.**  mu^ and the creep are low-passed over ``filter_s`` and the recursion runs on
every ``every``-th of them: one update each dt = ``every`` x period.  Inside a run length the cells forget
their past with the time constant ``memory_s`` (each update weighs the statistics by exp(-dt / ``memory_s``)):
a rail that recovers as the wheel cleans it changes slowly, which a change-point test does not date, and on a
rail the demand carries mu^ stays at the demand while the creep moves with the rail, which the curve model reads
as a flat curve at the demand until those samples are forgotten.  The memory is what sets the intervals'
coverage on rails that change, and their width with it (docs/design/control.md, issue 50 third pass).

**Changes of rail: Bayesian online change-point detection** (Adams and MacKay 2007, arXiv 0710.3742).  The
run length r (samples since the last change) has the posterior P(r | data) updated by the message passing of
that paper with a constant hazard H = dt / ``hazard_s`` per update::

    P(r + 1, x_1:t+1) = P(r, x_1:t) (1 - H) p(x_t+1 | r)                 growth
    P(0, x_1:t+1)     = sum_r P(r, x_1:t) H p(x_t+1 | prior)              a change

each run length carrying the cell statistics of its own samples only (the samples before its change are
forgotten).  As the paper suggests, the run lengths are pruned: the ``hypotheses`` most probable are kept
(a new one is born every update and survives only while it is among them).  The change is dated at the
most probable run length's start (``since_step``).

**What is published** (``PeakEstimate``): the mixture over run lengths and cells: the peak creep's 5, 50
and 95 % quantiles from its marginal on the grid (interpolated in log v_p), and the peak mu's mean and
90 % interval from the mixture's first two moments (normal).  Cost: one pass over (hypotheses x cells)
arrays per sample (``hil bench control`` measures it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

PEAK_CREEP_GRID_KMH = np.geomspace(0.08, 10.0, 40)
SHAPES = (0.3, 0.6, 1.0, 1.8, 3.5)
_Z90 = 1.6448536269514722
_LOG_2PI = math.log(2.0 * math.pi)

DEFAULTS = {"noise_mu": 0.004, "correlation": 10.0, "memory_s": 0.3, "creep_noise_kmh": 0.002, "filter_s": 0.01, "every": 5, "prior_mu": 0.2, "prior_mu_sd": 0.2, "hazard_s": 2.0,
            "hypotheses": 4, "min_creep_kmh": 0.02}


@dataclass(frozen=True)
class PeakEstimate:
    """The current rail's peak as the TCU estimates it at ``step`` (module docstring)."""
    step: int
    t_s: float
    peak_creep_kmh: float                      # the posterior median
    peak_creep_ci: tuple[float, float]         # 90 % interval
    peak_mu: float                             # the posterior mean
    peak_mu_ci: tuple[float, float]
    since_step: int                            # the dated change of rail (the most probable run's start)
    samples: int                               # samples since it


def prior_peak_creep_quantile_kmh(q: float) -> float:
    """The ``q`` quantile of the estimate's prior of the peak creep (log-uniform on the grid): what it says of a
    rail before any sample of it."""
    g = np.log(PEAK_CREEP_GRID_KMH)
    return float(np.exp(g[0] + q * (g[-1] - g[0])))


def shape(x: np.ndarray, k: np.ndarray) -> np.ndarray:
    """h_k(x) (module docstring), x >= 0."""
    return (1.0 + k) * x / (k + x ** (1.0 + k))


class PeakEstimator:
    """``add(step, t_s, creep_kmh, mu_hat) -> PeakEstimate`` once per sample (module docstring).  The recursion runs
    in identifier/kernels.py's ``peak_estimate_step`` and ``peak_estimate_publish`` (numba); ``compiled=False``
    runs the numpy reference here (tests/test_control.py checks they agree)."""

    def __init__(self, period_s: float, options: dict | None = None, compiled: bool = True):
        from . import kernels

        o = {**DEFAULTS, **(options or {})}
        for key in o:
            if key not in DEFAULTS:
                raise ValueError(f"unknown peak-estimate option {key!r} (known: {', '.join(DEFAULTS)})")
        self.options = o
        self.compiled = compiled and kernels.AVAILABLE
        vp, k = np.meshgrid(PEAK_CREEP_GRID_KMH, np.asarray(SHAPES, float), indexing="ij")
        self._vp, self._k = vp.ravel().copy(), k.ravel().copy()      # cells, v_p-major
        self._n_k = len(SHAPES)
        c = self._vp.size
        self._log_prior = np.full(c, -math.log(c))
        self._s2 = (o["noise_mu"] ** 2) * o["correlation"]
        self._prec0 = 1.0 / o["prior_mu_sd"] ** 2
        self._b0 = o["prior_mu"] * self._prec0
        # the recursion runs once every ``every`` periods: the hazard and the memory are per update, dt = every
        # periods, so both mean the seconds their options say
        dt = period_s * max(int(o["every"]), 1)
        if not o["hazard_s"] > dt:
            raise ValueError(f"hazard_s {o['hazard_s']!r} must exceed the update interval, {dt:g} s")
        self._log_h = math.log(dt / o["hazard_s"])
        self._log_1mh = math.log1p(-dt / o["hazard_s"])
        self._kmax = int(o["hypotheses"])
        self._keep = math.exp(-dt / o["memory_s"])
        self._log_grid = np.log(PEAK_CREEP_GRID_KMH)
        rows = self._kmax + 1
        self.prec = np.full((rows, c), self._prec0)
        self.b = np.full((rows, c), self._b0)
        self.logml = np.zeros((rows, c))
        self.log_mass = np.zeros(rows)
        self.start = np.zeros(rows, dtype=np.int64)
        self.count = np.zeros(rows, dtype=np.int64)
        self.n = 1                                   # rows in use: run-length hypotheses
        self._h, self._lp, self._dh = np.empty(c), np.empty(c), np.empty(c)
        self._sv2 = o["creep_noise_kmh"] ** 2
        self._marg, self._out = np.empty(PEAK_CREEP_GRID_KMH.size), np.empty(6)
        self.latest: PeakEstimate | None = None
        self._a = period_s / (o["filter_s"] + period_s)
        self._every = max(int(o["every"]), 1)
        self._v_f = self._m_f = None
        self._since = 0

    def add(self, step: int, t_s: float, creep_kmh: float, mu_hat: float) -> PeakEstimate:
        """One sample: the change-point recursion, the cells' update, the published estimate."""
        if not (math.isfinite(creep_kmh) and math.isfinite(mu_hat)):
            return self.latest or self._publish(step, t_s)
        if self._v_f is None:
            self._v_f, self._m_f = creep_kmh, mu_hat
        else:
            self._v_f += self._a * (creep_kmh - self._v_f)
            self._m_f += self._a * (mu_hat - self._m_f)
        self._since += 1
        if self._since < self._every and self.latest is not None:
            return self.latest
        self._since = 0
        x, mu_hat = abs(self._v_f), self._m_f
        if x >= self.options["min_creep_kmh"]:
            if self.compiled:
                from .kernels import peak_estimate_step
                self.n = peak_estimate_step(self.prec, self.b, self.logml, self.log_mass, self.start, self.count,
                                            self.n, self._log_prior, self._vp, self._k, x, float(mu_hat), self._s2,
                                            self._prec0, self._b0, self._log_h, self._log_1mh, self._kmax, step,
                                            self._h, self._lp, self._keep, self._dh, self._sv2)
            else:
                self._step_numpy(step, x, float(mu_hat))
        return self._publish(step, t_s)

    def _step_numpy(self, step: int, x: float, m: float) -> None:
        """The reference of ``kernels.peak_estimate_step`` (module docstring's recursion)."""
        n, s2 = self.n, self._s2
        h = shape(x / self._vp, self._k)
        xp = (x / self._vp) ** (1.0 + self._k)
        dh = (1.0 + self._k) * self._k * (1.0 - xp) / (self._k + xp) ** 2 / self._vp
        prec, b, logml = self.prec[:n], self.b[:n], self.logml[:n]
        mean = b / prec
        var = s2 + h * h / prec + (mean * dh) ** 2 * self._sv2
        lp = -0.5 * (_LOG_2PI + np.log(var) + (m - mean * h) ** 2 / var)
        a = self._log_prior + logml
        pred = _logsumexp_rows(a + lp) - _logsumexp_rows(a)
        var0 = s2 + h * h / self._prec0 + ((self._b0 / self._prec0) * dh) ** 2 * self._sv2
        lp0 = -0.5 * (_LOG_2PI + np.log(var0) + (m - (self._b0 / self._prec0) * h) ** 2 / var0)
        born = self._log_h + _logsumexp(self.log_mass[:n]) + _logsumexp(self._log_prior + lp0)
        self.log_mass[:n] += self._log_1mh + pred
        k = self._keep
        logml *= k
        logml += lp
        prec[:] = self._prec0 + k * (prec - self._prec0) + h * h / s2
        b[:] = self._b0 + k * (b - self._b0) + h * m / s2
        self.count[:n] += 1
        self.prec[n], self.b[n], self.logml[n] = self._prec0 + h * h / s2, self._b0 + h * m / s2, lp0
        self.log_mass[n], self.start[n], self.count[n] = born, step, 1
        n += 1
        if n > self._kmax:
            j, last = int(np.argmin(self.log_mass[:n])), n - 1
            if j != last:
                for arr in (self.prec, self.b, self.logml, self.log_mass, self.start, self.count):
                    arr[j] = arr[last]
            n -= 1
        self.log_mass[:n] -= _logsumexp(self.log_mass[:n])
        self.n = n

    def _publish(self, step: int, t_s: float) -> PeakEstimate:
        from .kernels import peak_estimate_publish

        n = self.n
        if self.compiled:
            peak_estimate_publish(self.prec, self.b, self.logml, self.log_mass, n, self._log_prior, self._n_k,
                                  self._log_grid, self._marg, self._out)
            lo, mid, hi, m1, sd, best = self._out
        else:
            a = self._log_prior + self.logml[:n]
            w = np.exp(a - _logsumexp_rows(a)[:, None] + self.log_mass[:n, None])
            w /= w.sum()
            marg = w.sum(axis=0).reshape(-1, self._n_k).sum(axis=1)
            mids = np.cumsum(marg) - 0.5 * marg
            lo, mid, hi = (float(np.exp(np.interp(q, mids, self._log_grid))) for q in (0.05, 0.5, 0.95))
            mean = self.b[:n] / self.prec[:n]
            m1 = float((w * mean).sum())
            sd = math.sqrt(max(float((w * (mean * mean + 1.0 / self.prec[:n])).sum()) - m1 * m1, 0.0))
            best = int(np.argmax(self.log_mass[:n]))
        best = int(best)
        self.latest = PeakEstimate(step, t_s, float(mid), (float(lo), float(hi)), float(m1),
                                   (float(m1 - _Z90 * sd), float(m1 + _Z90 * sd)), int(self.start[best]),
                                   int(self.count[best]))
        return self.latest


def _logsumexp(a: np.ndarray) -> float:
    m = float(a.max())
    return m + math.log(float(np.exp(a - m).sum()))


def _logsumexp_rows(a: np.ndarray) -> np.ndarray:
    m = a.max(axis=1)
    return m + np.log(np.exp(a - m[:, None]).sum(axis=1))
