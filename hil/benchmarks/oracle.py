"""The information limit: an offline posterior that knows the family's prior exactly (a helper module of
``hil bench identify``; it registers no command).

For one run's samples (those the ``bayes`` strategy received, from the detected slip start on), the
oracle draws ``draws`` curves from the fault-curve family itself (``plant.families.sample_curves``:
the very distribution the bench's truths are drawn from, in whatever law the family uses) and weighs
each by the same likelihood as the strategy (``identifier.speed_likelihood.SpeedFilter``, with the
strategy's own noise scale, process noise and creep), by importance sampling: no moves, no
approximation but the finite number of draws.  After every sample it computes the central intervals
of peak mu and peak creep; its RT is the first sample at which the interval at the confirmation
level (98 %) is within tolerance (3 % of its centre for peak mu, 10 % for peak creep), as the
strategy's rule.  Cost does not matter here; the effective sample size is reported beside the
result (below ~100 the oracle's intervals are themselves uncertain, and the bench says so).

A strategy is judged against it as a ratio of RTs: what the data of that run allowed, at the
family's own prior, versus what the strategy did.
"""
from __future__ import annotations

import math

import numpy as np

DRAWS = 200_000


def weighted_interval(x: np.ndarray, w: np.ndarray, level: float) -> tuple[float, float]:
    """Central weighted interval at ``level`` (the compiled histogram quantiles where numba is there)."""
    from identifier import kernels
    from identifier.strategies.bayes import weighted_quantiles

    qs = np.array([0.5 * (1.0 - level), 0.5 * (1.0 + level)])
    if kernels.AVAILABLE:
        out = np.empty(2)
        kernels.weighted_quantiles_hist(x, w, qs, 8192, np.empty(8192), out)
        return float(out[0]), float(out[1])
    lo, hi = weighted_quantiles(x, w, qs)
    return float(lo), float(hi)


def _spread_within(x: np.ndarray, w: np.ndarray, tol: float) -> bool:
    """The pre-check of the strategy's rule: a weighted std above tol x mean cannot pass it."""
    mean = float(w @ x)
    return float(w @ (x - mean) ** 2) <= (tol * mean) ** 2


def oracle(strategy, family: str, t_fault_s: float, seed: int, draws: int = DRAWS,
           confirm_level: float = 0.98, report_level: float = 0.90, tol_peak_mu: float = 0.03,
           tol_peak_creep: float = 0.10) -> dict:
    """The oracle on the samples a finished ``bayes`` strategy saw (``strategy.samples_seen``)."""
    from plant import families

    from identifier.speed_likelihood import SpeedFilter

    samples = strategy.samples_seen
    out = {"oracle_t_confirmed_s": None, "oracle_samples": None, "oracle_ess": None, "oracle_peak_mu_ci": None,
           "oracle_peak_creep_ci": None, "oracle_draws": draws}
    if len(samples) < 2:
        return out
    rng = np.random.default_rng([seed, 0x0AC1E])
    batch = families.sample_curves(family, draws, rng, samples[0].train_speed_ms)
    f0 = strategy.filter
    f = SpeedFilter(f0.period_s, f0.inertia_kgm2, f0.torque_per_mu_nm, f0.sigma_y_rad_s, f0.q_var)
    creep = [strategy.creep_for_likelihood(s) for s in samples]
    omega = f.open(samples[0].motor_speed_rad_s, draws)
    m_prev = batch.mu(np.array([creep[0]]))[:, 0]
    log_w = np.zeros(draws)
    for i in range(1, len(samples)):
        s, prev = samples[i], samples[i - 1]
        m_new = batch.mu(np.array([creep[i]]))[:, 0]
        log_w += f.step(omega, m_prev, m_new, max(s.step - prev.step, 1), prev.torque_nm, s.motor_speed_rad_s)
        m_prev = m_new
        w = np.exp(log_w - log_w.max())
        w /= w.sum()
        if i + 1 < 5:
            continue
        if not (_spread_within(batch.peak_mu, w, tol_peak_mu) and _spread_within(batch.peak_creep_kmh, w, tol_peak_creep)):
            continue
        mu_ci = weighted_interval(batch.peak_mu, w, confirm_level)
        creep_ci = weighted_interval(batch.peak_creep_kmh, w, confirm_level)
        if (mu_ci[1] - mu_ci[0] <= tol_peak_mu * (mu_ci[0] + mu_ci[1])
                and creep_ci[1] - creep_ci[0] <= tol_peak_creep * (creep_ci[0] + creep_ci[1])):
            out.update(oracle_t_confirmed_s=s.t_s, oracle_samples=i + 1, oracle_ess=float(1.0 / (w @ w)),
                       oracle_peak_mu_ci=list(weighted_interval(batch.peak_mu, w, report_level)),
                       oracle_peak_creep_ci=list(weighted_interval(batch.peak_creep_kmh, w, report_level)))
            return out
    out["oracle_ess"] = float(1.0 / (w @ w))
    return out


def oracle_rt_percent(result: dict, t_fault_s: float, t_det_s: float | None) -> float:
    """The oracle's RT in percent (infinite when its interval never came within tolerance)."""
    t = result.get("oracle_t_confirmed_s")
    if t is None or not t_det_s:
        return math.inf
    return (t - t_fault_s) / t_det_s * 100.0
