"""WHERE the sim-to-real gap lies: the residual of the nominal model, measured - model, on the three
signals (motor speed, train speed, the TCU's mu^), each divided by its noise floor, so 1 means "as
good as the sensors".

* per stage: normal / early / serious (``stages``: serious from the first creep >= the fault curve's
  peak creep after the fault time), by the measured creep and by the model's;
* per measured-creep band (``CREEP_BANDS_KMH``) and per frequency band (``FREQ_BANDS_HZ``; ``band_rms``
  by Parseval on the one-sided FFT, against the sensor noise's own RMS in that band);
* Ljung-Box whiteness, Q = n (n + 2) sum_k rho_k^2 / (n - k) against chi^2(lags); the largest
  normalised cross-correlation of the residual with the input (torque command) and with the model's
  creep, against the 95 % bound 1.96 / sqrt(n).

The headline names the EARLIEST stage where the gap is significant (``WHERE_SIGNIFICANT`` noise units
over ``WHERE_MIN_PERIODS`` periods: the serious stage amplifies any gap, so the worst stage says little
about where it starts) and the worst frequency band within that stage's own samples among the bands
its length resolves, then the overall largest.  ``observability`` says what a log cannot show.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import stats

from .candidates import SIGNALS, UNITS, Context, fit_nominal

WHERE_SIGNIFICANT = 2.0    # a stage's residual RMS (noise units) from which the gap counts as significant there
WHERE_MIN_PERIODS = 10     # ... over at least this many periods
CREEP_BANDS_KMH = (0.0, 0.5, 1.0, 1.5, 3.0, 10.0, math.inf)
FREQ_BANDS_HZ = (0.0, 2.0, 10.0, 30.0, 100.0, math.inf)


def stages(t_s, creep_kmh, fault_time_s, peak_creep_kmh) -> np.ndarray:
    """0 normal, 1 early, 2 serious per sample (serious from the first creep >= peak after t_f)."""
    out = np.zeros(len(t_s), int)
    after = t_s >= fault_time_s - 1e-12
    out[after] = 1
    over = np.flatnonzero(after & (creep_kmh >= peak_creep_kmh))
    if over.size:
        out[over[0]:] = 2
    return out


def ljung_box(x, lags: int = 20) -> tuple[float, float]:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    n = x.size
    if n <= lags + 2 or np.std(x) == 0:
        return math.nan, math.nan
    x = x - x.mean()
    den = float(np.dot(x, x))
    rho = np.array([np.dot(x[k:], x[:-k]) / den for k in range(1, lags + 1)])
    q = n * (n + 2) * float(np.sum(rho ** 2 / (n - np.arange(1, lags + 1))))
    return q, float(stats.chi2.sf(q, lags))


def max_xcorr(resid, reg, max_lag: int = 20) -> float | None:
    """max |normalised cross-correlation| of residual with a regressor over lags 0..max_lag (regressor
    leading); None if the regressor does not vary."""
    r = np.asarray(resid, float)
    x = np.asarray(reg, float)
    ok = np.isfinite(r) & np.isfinite(x)
    r, x = r[ok], x[ok]
    if r.size < max_lag + 10 or np.std(x) < 1e-12 or np.std(r) == 0:
        return None
    r = (r - r.mean()) / r.std()
    x = (x - x.mean()) / x.std()
    n = r.size
    return float(max(abs(np.dot(r[k:], x[:n - k]) / n) for k in range(max_lag + 1)))


def band_rms(x, period_s, bands) -> list[float]:
    """RMS of x inside each frequency band (Parseval on the one-sided FFT)."""
    x = np.asarray(x, float)
    x = x - x.mean()
    n = x.size
    spec = np.fft.rfft(x)
    f = np.fft.rfftfreq(n, period_s)
    power = np.abs(spec) ** 2 / n ** 2
    if n % 2 == 0:
        power[1:-1] *= 2
    else:
        power[1:] *= 2
    out = []
    for lo, hi in zip(bands[:-1], bands[1:]):
        sel = (f >= lo) & (f < hi)
        out.append(float(math.sqrt(power[sel].sum())))
    return out


#: effects (and parts of effects) that cannot show under a constant torque command, with the excitation
#: that makes them show
NEEDS_VARYING_TORQUE = {
    "torque_lag": "a first-order torque lag acts only when the command changes",
    "compliance.backlash_rad": "gear backlash acts only when the shaft torque changes sign",
}
EXCITATION = ("a torque command that varies: a PRBS dither of a few % or torque steps (the TCU's command is "
              "constant in hil run logs)")


def observability(input_constant: bool) -> list[dict]:
    """What this log cannot show: under a constant command, ``NEEDS_VARYING_TORQUE``; an effect there
    is 'not observable' (its absence from the answer says nothing), with the excitation that shows it."""
    if not input_constant:
        return []
    return [{"effect": k, "why": v, "excitation": EXCITATION} for k, v in NEEDS_VARYING_TORQUE.items()]


def normal_running_replay(ctx: Context):
    """The nominal model fitted on the pre-fault samples only: the reference of the WHERE statistics."""
    d = ctx.data
    pre = ctx.window & (d.t_s < ctx.scenario.run.fault_time_s)
    if pre.sum() < 20:
        return ctx.simulator(None, (), {}).run([], ctx.x0, d.torque_cmd_nm)
    fit = fit_nominal(ctx, pre)
    return fit.extra["plant_motor"], fit.extra["plant_train"]


def where(ctx: Context, nominal: dict, creep_meas) -> dict:
    """Where the gap lies (module docstring): the residual ``ctx.meas - nominal`` per signal, per stage
    (by measured and by model creep), per creep band and per frequency band, in noise units; the
    whiteness and cross-correlation tests; and the headline ``summary``."""
    d, sc = ctx.data, ctx.scenario
    w = ctx.window
    peak_creep = sc.fault_curve.peak()[0]
    creep_model = ctx.observer.creep_kmh(nominal["motor"], nominal["train"])
    st_meas = stages(d.t_s, creep_meas, sc.run.fault_time_s, peak_creep)
    st_model = stages(d.t_s, creep_model, sc.run.fault_time_s, peak_creep)
    resid = {s: ctx.meas[s] - nominal[s] for s in SIGNALS}
    resid["creep"] = creep_meas - creep_model
    sig = dict(ctx.sigma_nom)
    sig["creep"] = 3.6 * math.hypot(sc.vehicle.wheel_radius_m / sc.vehicle.gear_ratio * sig["motor"], sig["train"])

    def rms(x, sel):
        x = x[sel & np.isfinite(x)]
        return float(np.sqrt(np.mean(x ** 2))) if x.size else None

    per_signal = {s: {"rmse": rms(resid[s], w), "noise_floor": sig[s], "unit": UNITS.get(s, ""),
                      "rmse_in_noise_units": (rms(resid[s], w) or 0) / sig[s]} for s in resid}
    names = ("normal", "early", "serious")
    per_stage = {}
    for i, nm in enumerate(names):
        sel = w & (st_meas == i)
        per_stage[nm] = {"periods": int(sel.sum()),
                         **{s: (None if rms(resid[s], sel) is None else rms(resid[s], sel) / sig[s])
                            for s in resid}}

    per_stage_model = {}
    for i, nm in enumerate(names):
        sel = w & (st_model == i)
        per_stage_model[nm] = {"periods": int(sel.sum()),
                               **{s: (None if rms(resid[s], sel) is None else rms(resid[s], sel) / sig[s])
                                  for s in resid}}

    def t_det(stg):
        idx = np.flatnonzero(stg == 2)
        return float(d.t_s[idx[0]] - sc.run.fault_time_s) if idx.size else None

    per_band = []
    for lo, hi in zip(CREEP_BANDS_KMH[:-1], CREEP_BANDS_KMH[1:]):
        sel = w & (creep_meas >= lo) & (creep_meas < hi)
        per_band.append({"creep_kmh": [lo, None if math.isinf(hi) else hi], "periods": int(sel.sum()),
                         **{s: (None if rms(resid[s], sel) is None else rms(resid[s], sel) / sig[s])
                            for s in resid}})
    # frequency bands: residual RMS per band against the noise's own RMS in that band
    rng = np.random.default_rng(7)
    nw = int(w.sum())
    e = rng.standard_normal(nw)
    noise = {"motor": sig["motor"] * e, "train": sig["train"] * rng.standard_normal(nw),
             "mu_hat": sig["motor"] * (ctx.observer.mu_hat(64.0 + e, np.full(nw, ctx.observer.torque_demand))
                                       - ctx.observer.torque_demand / ctx.observer.torque_per_mu)}
    per_freq = []
    band_res = {s: band_rms(np.nan_to_num(resid[s][w]), d.period_s, FREQ_BANDS_HZ) for s in SIGNALS}
    band_noise = {s: band_rms(noise[s], d.period_s, FREQ_BANDS_HZ) for s in SIGNALS}
    for i, (lo, hi) in enumerate(zip(FREQ_BANDS_HZ[:-1], FREQ_BANDS_HZ[1:])):
        per_freq.append({"hz": [lo, None if math.isinf(hi) else hi],
                         **{s: {"rms": band_res[s][i], "noise_rms": band_noise[s][i],
                                "ratio": band_res[s][i] / band_noise[s][i] if band_noise[s][i] > 0 else None}
                            for s in SIGNALS}})
    tests = {}
    torque = d.torque_cmd_nm
    for s in SIGNALS:
        q, p = ljung_box(resid[s][w] / sig[s])
        tests[s] = {"ljung_box_q": q, "ljung_box_p": p, "white": bool(p > 0.01) if p == p else None,
                    "xcorr_input": max_xcorr(resid[s][w], torque[w]),
                    "xcorr_model_creep": max_xcorr(resid[s][w], creep_model[w]),
                    "xcorr_bound_95": 1.96 / math.sqrt(max(int(w.sum()), 1))}
    worst_stage = max(per_stage, key=lambda k: max((v or 0) for kk, v in per_stage[k].items()
                                                    if kk in SIGNALS) if per_stage[k]["periods"] else -1)
    worst_band = max(per_band, key=lambda b: max((b[s] or 0) for s in SIGNALS) if b["periods"] else -1)
    worst_freq = max(per_freq, key=lambda b: max((b[s]["ratio"] or 0) for s in SIGNALS))
    worst_signal = max(SIGNALS, key=lambda s: per_signal[s]["rmse_in_noise_units"])
    largest = (f"largest on {worst_signal} ({per_signal[worst_signal]['rmse_in_noise_units']:.1f}x noise), "
               f"in the {worst_stage} stage, at measured creep {worst_band['creep_kmh'][0]}-"
               f"{worst_band['creep_kmh'][1] or 'inf'} km/h, in the {worst_freq['hz'][0]}-"
               f"{worst_freq['hz'][1] or 'Nyquist'} Hz band")
    # the headline: the EARLIEST stage where the gap is significant (the serious stage amplifies any
    # gap), and the frequency band worst within that stage's own samples, among the bands its length
    # resolves (a band is resolved when the stage lasts at least two periods of its lower edge)
    earliest = None
    for i, nm in enumerate(names):
        v = per_stage[nm]
        if v["periods"] >= WHERE_MIN_PERIODS and max((v[s] or 0) for s in SIGNALS) >= WHERE_SIGNIFICANT:
            earliest = (i, nm)
            break
    stage_where = None
    if earliest is not None:
        i, nm = earliest
        sel = w & (st_meas == i)
        dur = float(sel.sum()) * d.period_s
        f_min = 2.0 / dur if dur > 0 else math.inf
        sig_e = max(SIGNALS, key=lambda s: per_stage[nm][s] or 0)
        e2 = np.random.default_rng(11).standard_normal(int(sel.sum()))
        bands = []
        for s_ in SIGNALS:
            res = band_rms(np.nan_to_num(resid[s_][sel]), d.period_s, FREQ_BANDS_HZ)
            nz = band_rms(noise["mu_hat"][:e2.size] if s_ == "mu_hat" else sig[s_] * e2, d.period_s,
                          FREQ_BANDS_HZ)
            for j, (lo, hi) in enumerate(zip(FREQ_BANDS_HZ[:-1], FREQ_BANDS_HZ[1:])):
                bands.append({"signal": s_, "hz": [lo, None if math.isinf(hi) else hi],
                              "ratio": res[j] / nz[j] if nz[j] > 0 else None, "resolved": lo == 0 or lo >= f_min})
        resolved = [b for b in bands if b["resolved"] and b["ratio"] is not None and b["hz"][0] > 0]
        worst_b = max(resolved, key=lambda b: b["ratio"]) if resolved else None
        unresolved = sorted({b["hz"][0] for b in bands if not b["resolved"]})
        stage_where = {"stage": nm, "signal": sig_e, "rms_in_noise_units": per_stage[nm][sig_e],
                       "duration_s": dur, "lowest_resolved_hz": f_min, "bands": bands,
                       "worst_band": worst_b}
        summary = (f"first significant in the {nm} stage ({sig_e} {per_stage[nm][sig_e]:.1f}x noise over "
                   f"{dur:.3g} s)")
        if worst_b is not None:
            summary += (f", there worst in the {worst_b['hz'][0]:g}-{worst_b['hz'][1] or 'Nyquist'} Hz band "
                        f"({worst_b['signal']} {worst_b['ratio']:.1f}x the noise in that band)")
        if unresolved:
            summary += (f"; its {dur:.3g} s do not resolve bands below {f_min:.3g} Hz")
        summary += f"; overall {largest}"
    else:
        summary = largest
    return {"summary": summary, "largest": largest, "earliest": stage_where,
            "per_signal": per_signal, "per_stage": per_stage,
            "per_stage_by_model_creep": per_stage_model,
            "t_det_measured_s": t_det(st_meas), "t_det_model_s": t_det(st_model),
            "per_creep_band": per_band, "per_frequency_band": per_freq, "tests": tests,
            "input_constant": bool(np.std(torque) < 1e-9)}


def separation(ctx: Context, preds: dict, creep_meas) -> list[dict]:
    """Where explanations that the held-out score cannot tell apart differ most: for each pair of
    ``preds`` ({name: predicted signals}, the first against each other), the signal and stage (by the
    measured creep, ``stages``; at least ``WHERE_MIN_PERIODS`` periods in the analysis window) where the
    RMS of their predictions' difference, in noise units, is largest.  A log with more samples there (a
    longer stage, an excitation that reaches it) is what would separate them."""
    sc = ctx.scenario
    st = stages(ctx.data.t_s, creep_meas, sc.run.fault_time_s, sc.fault_curve.peak()[0])
    names = list(preds)
    out = []
    for other in names[1:]:
        a, b = preds[names[0]], preds[other]
        best = None
        for s in SIGNALS:
            for i, nm in enumerate(("normal", "early", "serious")):
                sel = ctx.window & (st == i) & ctx.valid[s]
                if sel.sum() < WHERE_MIN_PERIODS:
                    continue
                d = float(np.sqrt(np.mean(((a[s] - b[s])[sel] / ctx.sigma_nom[s]) ** 2)))
                if best is None or d > best["difference_noise_units"]:
                    best = {"between": [names[0], other], "signal": s, "stage": nm, "difference_noise_units": d,
                            "periods": int(sel.sum())}
        if best is not None:
            out.append(best)
    return out
