"""The information limit: an offline posterior that knows the family's prior exactly (a helper module of
``hil bench identify``; it registers no command).

For one run's samples (every sample the ``bayes`` strategy would receive, from the detected slip
start until the creep passes its prior's highest peak creep) the oracle computes the posterior over
the fault-curve family's own curves (``plant.families``: the very distribution the bench's truths are
drawn from, in whatever law the family uses) under the same likelihood as the strategy
(``identifier.speed_likelihood.SpeedFilter``, with the strategy's noise scale, process noise and
creep).  It is a sequential Monte Carlo sampler without approximation but the finite sample:

- ``draws`` curves from the family (a curve is a point z of a unit cube per law: ``families.LATENT``);
- after every sample, weights w_j propto L_j (each curve's likelihood so far);
- when the effective sample size falls below half, systematic resampling, then ``MOVES`` random-walk
  Metropolis steps per curve in z (prior: uniform on the cube under the joint peak rule; proposal
  scaled by the cloud's spread per coordinate, 2.38 / sqrt(d)), each accepted with
  min(1, L(z') / L(z)), the likelihood of z' recomputed over all samples so far.  This keeps the
  posterior exact in distribution while the cloud follows it as it narrows (plain importance
  sampling from the prior collapses to a handful of draws within a few milliseconds).

After every sample it takes the central intervals of peak mu and peak creep; its RT is the first
sample at which the interval at the confirmation level (98 %) is within tolerance (3 % of its centre
for peak mu, 10 % for peak creep), the strategy's rule.  Cost does not matter here.
"""
from __future__ import annotations

import math

import numpy as np

from identifier.pf import weighted_interval

DRAWS = 4000
MOVES = 3
#: the least effective sample size at which the oracle's interval counts
MIN_ESS = 30


class _Cloud:
    """One law's curves in z with their filter state (module docstring)."""

    def __init__(self, family: str, law: int, z: np.ndarray, speed_filter, creep, samples, train_speed_ms):
        self.family, self.law = family, law
        self.f, self.creep, self.samples, self.v_t = speed_filter, creep, samples, train_speed_ms
        self.set(z, *self.run(self._batch(z), 0), self._batch(z))

    def set(self, z, ll, omega, m_last, p_var, batch) -> None:
        self.z, self.ll, self.omega, self.m_last, self.p_var, self.batch = z, ll, omega, m_last, p_var, batch

    def _batch(self, z):
        from plant import families

        return families.batch_of_law(self.family, self.law, z, self.v_t)

    def _filter(self, p_var: float):
        from identifier.speed_likelihood import SpeedFilter

        f0 = self.f
        return SpeedFilter(f0.period_s, f0.inertia_kgm2, f0.torque_per_mu_nm, f0.sigma_y_rad_s, f0.q_var, p_var)

    def run(self, batch, upto: int):
        """(log L, omega, M at sample upto, P) of every curve of ``batch`` over samples 0..upto, afresh."""
        f = self._filter(math.nan)
        m = batch.mu(np.asarray(self.creep[:upto + 1]))
        omega = f.open(self.samples[0].motor_speed_rad_s, len(batch))
        ll = np.zeros(len(batch))
        for i in range(1, upto + 1):
            s, prev = self.samples[i], self.samples[i - 1]
            ll += f.step(omega, m[:, i - 1], m[:, i], max(s.step - prev.step, 1), prev.torque_nm, s.motor_speed_rad_s)
        return ll, omega, m[:, upto].copy(), f.p_var

    def advance(self, i: int) -> None:
        """Take sample i (> the last one taken) into every curve's filter."""
        f = self._filter(self.p_var)
        s, prev = self.samples[i], self.samples[i - 1]
        m_new = self.batch.mu(np.array([self.creep[i]]))[:, 0]
        self.ll += f.step(self.omega, self.m_last, m_new, max(s.step - prev.step, 1), prev.torque_nm,
                          s.motor_speed_rad_s)
        self.m_last, self.p_var = m_new, f.p_var


def oracle(strategy, family: str, seed, draws: int = DRAWS, confirm_level: float = 0.98,
           report_level: float = 0.90, tol_peak_mu: float = 0.03, tol_peak_creep: float = 0.10) -> dict:
    """The oracle on the samples a ``bayes`` strategy saw (``strategy.samples_seen``, its filter)."""
    from plant import families

    samples = strategy.samples_seen
    out = {"oracle_t_confirmed_s": None, "oracle_samples": None, "oracle_ess": None, "oracle_peak_mu_ci": None,
           "oracle_peak_creep_ci": None, "oracle_draws": draws, "oracle_moves": 0}
    if len(samples) < 5:
        return out
    rng = np.random.default_rng(seed)
    v_t = samples[0].train_speed_ms
    creep = [strategy.creep_for_likelihood(s) for s in samples]
    # the family's prior: its own sampler decides each curve's law, the clouds hold each law's curves
    laws = families.sample_curves(family, draws, rng, v_t).law
    clouds = []
    for law in (families.LAW_EXP, families.LAW_POLACH):
        n = int(np.sum(laws == law))
        if n:
            clouds.append(_Cloud(family, law, families.unit_points(law, n, rng), strategy.filter, creep, samples, v_t))
    for i in range(1, len(samples)):
        for c in clouds:
            c.advance(i)
        w = _weights(clouds)
        ess = float(1.0 / (w @ w))
        if ess < 0.5 * w.size:
            _resample_move(clouds, w, i, rng)
            out["oracle_moves"] += 1
            w = _weights(clouds)
            ess = float(1.0 / (w @ w))
        if i < 4:
            continue
        peak_mu = np.concatenate([c.batch.peak_mu for c in clouds])
        peak_creep = np.concatenate([c.batch.peak_creep_kmh for c in clouds])
        mu_ci = weighted_interval(peak_mu, w, confirm_level)
        creep_ci = weighted_interval(peak_creep, w, confirm_level)
        out["oracle_ess"] = ess
        if (ess >= MIN_ESS and mu_ci[1] - mu_ci[0] <= tol_peak_mu * (mu_ci[0] + mu_ci[1])
                and creep_ci[1] - creep_ci[0] <= tol_peak_creep * (creep_ci[0] + creep_ci[1])):
            out.update(oracle_t_confirmed_s=samples[i].t_s, oracle_samples=i + 1,
                       oracle_peak_mu_ci=list(weighted_interval(peak_mu, w, report_level)),
                       oracle_peak_creep_ci=list(weighted_interval(peak_creep, w, report_level)))
            return out
    return out


def _weights(clouds) -> np.ndarray:
    lw = np.concatenate([c.ll for c in clouds])
    w = np.exp(lw - lw.max())
    return w / w.sum()


def _resample_move(clouds, w, upto, rng) -> None:
    """Systematic resampling over all curves (a law keeps the curves resampled into it), then
    Metropolis moves in z within each law, each proposal's likelihood over samples 0..upto afresh."""
    from plant import families

    n = w.size
    idx = np.minimum(np.searchsorted(np.cumsum(w), (rng.random() + np.arange(n)) / n), n - 1)
    bounds = np.cumsum([0] + [len(c.z) for c in clouds])
    for k, c in enumerate(clouds):
        mine = idx[(idx >= bounds[k]) & (idx < bounds[k + 1])] - bounds[k]
        z, ll, omega, m_last = c.z[mine], c.ll[mine], c.omega[mine], c.m_last[mine]
        if mine.size:
            scale = 2.38 / math.sqrt(z.shape[1]) * np.maximum(z.std(axis=0), 1e-4)
            for _ in range(MOVES):
                prop = np.abs(z + scale * rng.standard_normal(z.shape))     # reflected into the unit cube
                prop = np.where(prop > 1.0, 2.0 - prop, prop)
                ll_p, omega_p, m_p, _ = c.run(c._batch(prop), upto)
                accept = families.peak_allowed(prop[:, 0], prop[:, 1]) & (np.log(rng.random(ll.size)) < ll_p - ll)
                z = np.where(accept[:, None], prop, z)
                ll, omega, m_last = (np.where(accept, a, b) for a, b in ((ll_p, ll), (omega_p, omega), (m_p, m_last)))
        c.set(z, ll, omega, m_last, c.p_var, c._batch(z))


def oracle_rt_percent(result: dict, t_fault_s: float, t_det_s: float | None) -> float:
    """The oracle's RT in percent (infinite when its interval never came within tolerance)."""
    t = result.get("oracle_t_confirmed_s")
    if t is None or not t_det_s:
        return math.inf
    return (t - t_fault_s) / t_det_s * 100.0
