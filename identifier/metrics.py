"""Goodness of fit (paper eq. 32-35), RT, and the peak errors the paper does not report."""
from __future__ import annotations

import math

import numpy as np

from .curve import mu_model, peak


def fit_metrics(creep_speed_kmh, mu_samples, theta) -> dict:
    """MSE, RMSE, MAE and R^2 of the curve ``theta`` against mu^ samples."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    ok = np.isfinite(v) & np.isfinite(y)
    v, y = v[ok], y[ok]
    if y.size == 0:
        return {"mse": math.nan, "rmse": math.nan, "mae": math.nan, "r2": math.nan}
    resid = y - mu_model(v, theta)
    mse = float(np.mean(resid ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum(resid ** 2)) / ss_tot if ss_tot > 0 else math.nan
    return {"mse": mse, "rmse": math.sqrt(mse), "mae": float(np.mean(np.abs(resid))), "r2": r2}


def _true_curve(truth):
    """The true curve as (mu of creep in km/h, its peak (v, mu)): ``truth`` is an exponential curve's
    parameter vector or any friction law with ``mu(creep_kmh)`` and ``peak()`` (e.g. a Polach curve)."""
    if hasattr(truth, "peak") and hasattr(truth, "mu"):
        return (lambda v: np.asarray(truth.mu(v), float)), truth.peak()
    theta = np.asarray(truth, float)
    return (lambda v: mu_model(v, theta)), peak(theta)


def peak_errors(theta, truth) -> dict:
    """Peak mu and peak creep of the identified curve ``theta`` and their errors against the true curve
    ``truth`` (a parameter vector or a friction law), in percent: |x_id - x_true| / |x_true| * 100."""
    v_id, mu_id = peak(theta)
    v_true, mu_true = _true_curve(truth)[1]
    return {
        "peak_mu_err_percent": abs(mu_id - mu_true) / abs(mu_true) * 100.0,
        "peak_creep_err_percent": abs(v_id - v_true) / abs(v_true) * 100.0,
        "peak_mu": mu_id,
        "peak_creep_kmh": v_id,
    }


def curve_rmse_vs_truth(theta, truth, upto_kmh: float) -> float:
    """RMSE between the identified and true curves on 200 points over [0, upto_kmh] (a check the
    samples cannot bias)."""
    grid = np.linspace(0.0, upto_kmh, 200)
    with np.errstate(over="ignore", invalid="ignore"):
        return float(np.sqrt(np.mean((mu_model(grid, theta) - _true_curve(truth)[0](grid)) ** 2)))


def r2_vs_truth(theta, truth, upto_kmh: float) -> float:
    """R^2 of the identified curve against the true one on 200 points over [0, upto_kmh]: the share
    of the true curve's variation there that the identified curve reproduces (free of the mu^
    samples' noise and narrow range, which cap the paper's R^2 against the samples)."""
    grid = np.linspace(0.0, upto_kmh, 200)
    true_mu = _true_curve(truth)[0](grid)
    ss_tot = float(np.sum((true_mu - true_mu.mean()) ** 2))
    with np.errstate(over="ignore", invalid="ignore"):
        ss_res = float(np.sum((mu_model(grid, theta) - true_mu) ** 2))
    return 1.0 - ss_res / ss_tot if ss_tot > 0 and math.isfinite(ss_res) else math.nan


def against_truth(theta, truth) -> dict:
    """Every truth metric of the identified curve ``theta``: the peak errors, and on 200 points the RMSE
    and R^2 over [0, 2 v_peak] (``curve_rmse_vs_truth``, ``r2_vs_truth``) and the R^2 over [0, v_peak],
    the stable side a controller acts on (``r2_vs_truth_to_peak``)."""
    v_true = _true_curve(truth)[1][0]
    return {**peak_errors(theta, truth),
            "curve_rmse_vs_truth": curve_rmse_vs_truth(theta, truth, 2.0 * v_true),
            "r2_vs_truth": r2_vs_truth(theta, truth, 2.0 * v_true),
            "r2_vs_truth_to_peak": r2_vs_truth(theta, truth, v_true)}


def intervals_hold_truth(peak_mu_ci, peak_creep_ci, peak_open: bool, truth) -> bool | None:
    """Whether a curve's 90 % peak intervals hold the true peak, both of them; an open interval (its upper
    end the TCU's working range, not the data's) never does.  None without intervals."""
    if peak_mu_ci is None or peak_creep_ci is None:
        return None
    v_true, mu_true = _true_curve(truth)[1]
    return bool(not peak_open and peak_mu_ci[0] <= mu_true <= peak_mu_ci[1]
                and peak_creep_ci[0] <= v_true <= peak_creep_ci[1])


def rt_percent(t_identified_s: float, t_fault_s: float, deterioration_time_s: float) -> float:
    """RT = (t_identified - t_f) / T_det, percent (Table 3)."""
    if t_identified_s is None or not math.isfinite(deterioration_time_s) or deterioration_time_s <= 0:
        return math.nan
    return (t_identified_s - t_fault_s) / deterioration_time_s * 100.0
