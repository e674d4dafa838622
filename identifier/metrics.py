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


def peak_errors(theta, true_theta) -> dict:
    """Peak mu and peak creep errors of the identified curve against the true one, in percent."""
    v_id, mu_id = peak(theta)
    v_true, mu_true = peak(true_theta)
    return {
        "peak_mu_err_percent": abs(mu_id - mu_true) / abs(mu_true) * 100.0,
        "peak_creep_err_percent": abs(v_id - v_true) / abs(v_true) * 100.0,
        "peak_mu": mu_id,
        "peak_creep_kmh": v_id,
    }


def curve_rmse_vs_truth(theta, true_theta, upto_kmh: float) -> float:
    """RMSE between the identified and true curves on [0, upto_kmh] (a check the samples cannot bias)."""
    grid = np.linspace(0.0, upto_kmh, 200)
    return float(np.sqrt(np.mean((mu_model(grid, theta) - mu_model(grid, true_theta)) ** 2)))


def r2_vs_truth(theta, true_theta, upto_kmh: float) -> float:
    """R^2 of the identified curve against the true one on 200 points over [0, upto_kmh]: the share
    of the true curve's variation there that the identified curve reproduces (free of the mu^
    samples' noise and narrow range, which cap the paper's R^2 against the samples)."""
    grid = np.linspace(0.0, upto_kmh, 200)
    truth = mu_model(grid, true_theta)
    ss_tot = float(np.sum((truth - truth.mean()) ** 2))
    with np.errstate(over="ignore", invalid="ignore"):
        ss_res = float(np.sum((mu_model(grid, theta) - truth) ** 2))
    return 1.0 - ss_res / ss_tot if ss_tot > 0 and math.isfinite(ss_res) else math.nan


def rt_percent(t_identified_s: float, t_fault_s: float, deterioration_time_s: float) -> float:
    """RT = (t_identified - t_f) / T_det, percent (Table 3)."""
    if t_identified_s is None or not math.isfinite(deterioration_time_s) or deterioration_time_s <= 0:
        return math.nan
    return (t_identified_s - t_fault_s) / deterioration_time_s * 100.0
