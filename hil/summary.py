"""The run summary: stages, RT, fit metrics and peak errors, as the JSON ``hil run --json`` prints."""
from __future__ import annotations

import math

import numpy as np

from identifier.metrics import curve_rmse_vs_truth, fit_metrics, peak_errors, r2_vs_truth, rt_percent


def observer_lag_ms(t_s, mu_true, mu_hat, t_from: float, t_to: float, period_s: float, max_lag_s=0.03) -> float:
    """Shift (ms) of mu^ behind the true mu that best aligns them on [t_from, t_to]."""
    t = np.asarray(t_s)
    sel = np.flatnonzero((t >= t_from) & (t <= t_to))
    if sel.size < 5:
        return math.nan
    mu_true, mu_hat = np.asarray(mu_true, float), np.asarray(mu_hat, float)
    if not (np.all(np.isfinite(mu_true[sel])) and np.all(np.isfinite(mu_hat[sel]))):
        return math.nan     # a plant that does not report its true mu (e.g. a foreign FMU)
    best, best_err = 0, math.inf
    for lag in range(0, int(round(max_lag_s / period_s)) + 1):
        idx = sel[sel - lag >= 0]
        if idx.size < 5:      # too little overlap left to judge this shift
            break
        err = float(np.mean((mu_hat[idx] - mu_true[idx - lag]) ** 2))
        if err < best_err:
            best, best_err = lag, err
    return best * period_s * 1e3


def observer_lag_by_step(scenario, truth_t, truth_mu, observer_mu_by_step: dict, serious_time_s) -> float | None:
    """``observer_lag_ms`` with mu^ given per step (what a TCU report or a replay collects): None
    when a step of the truth window has no mu^ (the TCU's side of the run is incomplete)."""
    period = scenario.run.exchange_period_s
    steps = [int(round(t / period)) for t in truth_t]
    if not steps or not all(s in observer_mu_by_step for s in steps):
        return None
    return observer_lag_ms(truth_t, truth_mu, [observer_mu_by_step[s] for s in steps], scenario.run.fault_time_s,
                           serious_time_s or scenario.run.duration_s, period)


def fmt(x, spec: str = ".3g") -> str:
    """A summary value for people: ``format(x, spec)``, "n/a" for a missing one."""
    return "n/a" if x is None else format(x, spec)


def clean(x):
    """JSON-safe: NaN and inf become None."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, (np.floating,)):
        return clean(float(x))
    if isinstance(x, dict):
        return {k: clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [clean(v) for v in x]
    return x


def summarise(*, scenario, strategy: str, seed: int, bus: str, tracker, events, samples_v, samples_mu,
              t_detected_s, mcap_path, extra=None) -> dict:
    """Summary of one run from the TCU's events and samples and the plant's stage tracker."""
    confirmed = next((e for e in events if e.kind == "confirmed"), None)
    corrections = [e for e in events if e.kind == "correction"]
    last = confirmed or (corrections[-1] if corrections else None)
    true_theta = scenario.fault_curve.params
    out = {
        "scenario": scenario.name, "strategy": strategy, "seed": seed, "bus": bus,
        "identified": confirmed is not None,
        "t_fault_s": scenario.run.fault_time_s,
        "t_serious_s": tracker.serious_time_s,
        "t_det_s": tracker.deterioration_time_s,
        "t_detected_s": t_detected_s,
        # a slip flagged before the fault is a false alarm: whatever it identified is not the fault curve
        "false_alarm": t_detected_s is not None and t_detected_s < scenario.run.fault_time_s,
        "t_identified_s": confirmed.t_s if confirmed else None,
        "rt_percent": rt_percent(confirmed.t_s if confirmed else None, scenario.run.fault_time_s,
                                 tracker.deterioration_time_s),
        "params": list(last.params) if last else None,
        "true_params": list(true_theta),
        "corrections": len(corrections),
        "samples": len(samples_v),
        "mcap": str(mcap_path) if mcap_path else None,
    }
    if last is not None:
        theta = np.asarray(last.params)
        out.update(fit_metrics(samples_v, samples_mu, theta))
        out.update(peak_errors(theta, true_theta))
        v_peak = scenario.fault_curve.peak()[0]
        out["curve_rmse_vs_truth"] = curve_rmse_vs_truth(theta, true_theta, 2.0 * v_peak)
        out["r2_vs_truth"] = r2_vs_truth(theta, true_theta, 2.0 * v_peak)
    else:
        out.update({k: None for k in ("mse", "rmse", "mae", "r2", "peak_mu_err_percent", "peak_creep_err_percent",
                                      "peak_mu", "peak_creep_kmh", "curve_rmse_vs_truth", "r2_vs_truth")})
    out.update(extra or {})
    return clean(out)
