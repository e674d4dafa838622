"""When no candidate explains the gap, describe it: a sparse regression of what the nominal model
leaves on a small library of terms says what the missing term depends on.

Two views of what the nominal model leaves in the motor speed over the analysis window:

    level:  r(k) = y_meas(k) - y_nominal(k)                 = sum_i xi_i theta_i(k)   a sensor-type term
            (the nominal model replayed over the whole run)                        (``motor speed x 0.01``
                                                                                   reads as a tachometer
                                                                                   gain of 1.01)
    rate:   a(k) = (y_meas(k+h) - y^(k+h | x_meas(k))) / (h dt) = sum_i xi_i theta_i(k)   a dynamics-type
            (the model started from the measured state at k,                       term: an acceleration
            run h = ``AHEAD_PERIODS`` periods under the logged commands)            the model lacks there

The rate view is SINDy's own form (the state's derivative regressed on the measured state) with the
known model subtracted: it asks what acceleration is missing *at the state the wheelset was in*.  The
derivative of the replay's residual is not that: once the replay leaves the measured run (a model that
slips where the real wheel was held, by a torque cap say) that residual is mostly the model's own
runaway, a function of the model's states and not of any measured one, and a library of measured terms
then fits it with whatever drifts alike (the train speed, a slow sine).  h trades noise (a(k) carries
sqrt(2) sigma / (h dt)) against the model's own divergence from a state near the adhesion peak, which
grows within tens of periods.

Both are regressed on the library theta = {1, motor speed, train speed, creep speed, creep rate,
torque command}, all measured, and, when the residual r carries a spectral line, a periodic term at
its frequency f* (sin and cos of 2 pi f* t together, one term; and the same times the torque command,
which only a command that varies in the window can tell apart from it).  The line is the
periodogram's highest peak from ``LINE_MIN_HZ`` up, standing ``LINE_FACTOR`` times above the median
of its neighbourhood: for white noise each bin's periodogram is exponential, so one bin stands
LINE_FACTOR times above the true median with probability 2^-LINE_FACTOR; but the highest of a
thousand bins is tested, against the median of some fifty neighbours that the Hann window
correlates, and that median is itself noisy (it falls to half its mean now and then), so the factor
sits well above what one bin's tail asks.  A red spectrum (what a missing slow term leaves) has its
highest bin at the search's lower edge, on a slope that falls from below it: that is no line (a line
is a local peak), and none is looked for above it, where the window's leakage of the slope would be
taken for one.  (Products such as motor speed x torque fitted a tachometer gain as well as motor
speed alone did, and then named two variables where one is the answer: ``TERMS`` leaves them out.)
The sparse fit is a best subset of at most ``MAX_TERMS`` terms, chosen on the training blocks and
judged on the held-out blocks (the diagnosis' own split): a term is added only when it raises the
held-out R^2 by ``MIN_GAIN``.  This is SINDy's idea (Brunton, Proctor and Kutz, PNAS 2016) with an
exhaustive subset in place of sequential thresholding, which a library of ten terms affords.  The view
with the higher held-out R^2 is reported; below ``MIN_R2`` the answer is "no sparse description": the
missing term is not in the library (or too weak against the noise), which is said rather than a term
being forced.
"""
from __future__ import annotations

from itertools import combinations

import numpy as np

#: the most terms a description uses
MAX_TERMS = 2
#: the held-out R^2 an added term must add
MIN_GAIN = 0.05
#: the held-out R^2 a product term (two variables in one term) must add over the one-variable terms of
#: a subset of its size: a plain sine, and the same sine times a command that steps by a few per cent,
#: fit alike within the noise, and only the first is the simpler answer
PRODUCT_MARGIN = 0.01
#: the periods the rate view runs the model from each measured state (module docstring)
AHEAD_PERIODS = 5
#: the held-out R^2 below which there is no description
MIN_R2 = 0.3
#: the spectral line a periodic term needs: from this frequency up (below it a window of a second
#: holds too few cycles to tell a line from a slow drift) ...
LINE_MIN_HZ = 2.0
#: ... standing this many times above the median periodogram of the bins around it (module docstring)
LINE_FACTOR = 40.0
#: ... over this many bins either side
LINE_NEIGHBOURS = 25
#: what each term depends on (the variables a description names)
VARIABLES = {"1": (), "motor_speed": ("motor_speed",), "train_speed": ("train_speed",),
             "creep_speed": ("creep_speed",), "creep_rate": ("creep_speed",), "torque": ("torque",),
             "motor_speed*torque": ("motor_speed", "torque"), "creep_speed*torque": ("creep_speed", "torque"),
             "periodic": ("periodic",), "torque*periodic": ("torque", "periodic")}
TERMS = ("1", "motor_speed", "train_speed", "creep_speed", "creep_rate", "torque", "periodic", "torque*periodic")
UNITS = {"1": "", "motor_speed": "rad/s", "train_speed": "m/s", "creep_speed": "km/h", "creep_rate": "km/h/s",
         "torque": "N·m", "motor_speed*torque": "rad/s·N·m", "creep_speed*torque": "km/h·N·m", "periodic": "",
         "torque*periodic": "N·m"}


def library(motor_rad_s, train_ms, creep_kmh, torque_nm, period_s, line_hz: float | None = None) \
        -> dict[str, np.ndarray]:
    """The library's terms along the measured run; a periodic term is two columns (sin, cos of
    2 pi line_hz t), there only when ``line_hz`` is given."""
    creep_rate = np.gradient(creep_kmh, period_s)
    out = {"1": np.ones_like(motor_rad_s), "motor_speed": motor_rad_s, "train_speed": train_ms,
           "creep_speed": creep_kmh, "creep_rate": creep_rate, "torque": torque_nm,
           "motor_speed*torque": motor_rad_s * torque_nm, "creep_speed*torque": creep_kmh * torque_nm}
    if line_hz is not None:
        phase = 2 * np.pi * line_hz * period_s * np.arange(motor_rad_s.size)
        wave = np.column_stack([np.sin(phase), np.cos(phase)])
        out["periodic"] = wave
        out["torque*periodic"] = wave * torque_nm[:, None]
    return {k: v for k, v in out.items() if k in TERMS}


def spectral_line(r, mask, period_s) -> float | None:
    """The frequency (Hz) of the residual's spectral line over the span of ``mask`` (module
    docstring), refined between periodogram bins by the best least-squares sinusoid; None without one."""
    idx = np.flatnonzero(mask & np.isfinite(r))
    if idx.size < 64:
        return None
    x = r[idx[0]:idx[-1] + 1]
    x = np.where(np.isfinite(x), x, np.nanmean(x))
    x = x - x.mean()
    power = np.abs(np.fft.rfft(x * np.hanning(x.size))) ** 2
    freq = np.fft.rfftfreq(x.size, period_s)
    lo = int(np.searchsorted(freq, LINE_MIN_HZ))
    if lo >= power.size - 2:
        return None
    k = lo + int(np.argmax(power[lo:-1]))
    if k > 0 and power[k - 1] > power[k]:
        return None      # the search's lowest bin on a falling (red) spectrum: a slope, not a line
    around = np.r_[power[max(k - LINE_NEIGHBOURS, 1):max(k - 2, 1)], power[k + 3:k + LINE_NEIGHBOURS + 1]]
    if around.size < 10 or power[k] < LINE_FACTOR * np.median(around):
        return None
    t = period_s * np.arange(x.size)
    df = freq[1] - freq[0]

    def fitted_power(f):
        w = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)])
        coef, *_ = np.linalg.lstsq(w, x, rcond=None)
        return float(np.sum((w @ coef) ** 2))
    grid = freq[k] + df * np.linspace(-1.0, 1.0, 41)
    line_hz = float(max(grid, key=fitted_power))
    return line_hz if line_hz >= LINE_MIN_HZ else None


def _r2(y, yhat) -> float:
    ss = float(np.sum((y - y.mean()) ** 2))
    return 1.0 - float(np.sum((y - yhat) ** 2)) / ss if ss > 0 else 0.0


def best_subset(target, terms: dict, train, held) -> dict:
    """The subset of at most MAX_TERMS terms (the constant always in) with the best held-out R^2,
    grown one term at a time only while each adds MIN_GAIN.  Among subsets of one size, a product term
    (``torque*periodic``: two variables in one term) must beat the others by PRODUCT_MARGIN, so a plain
    sine is not said to depend on the torque when the two fit alike within the noise.  A term of two
    columns (periodic) gets two coefficients (sin, cos): its ``coef`` is their amplitude, its
    ``phase_rad`` their angle."""
    names = [n for n in terms if n != "1"]
    X = {n: terms[n].reshape(terms[n].shape[0], -1) for n in terms}
    best = {"terms": [], "coef": {}, "held_out_r2": 0.0}
    for k in range(1, MAX_TERMS + 1):
        cand = None
        for subset in combinations(names, k):
            cols = ["1", *subset]
            A = np.column_stack([X[c] for c in cols])
            scale = np.maximum(np.abs(A[train]).max(axis=0), 1e-12)
            coef, *_ = np.linalg.lstsq(A[train] / scale, target[train], rcond=None)
            coef = coef / scale
            r2 = _r2(target[held], A[held] @ coef)
            score = r2 - PRODUCT_MARGIN * sum(len(VARIABLES[t]) - 1 for t in subset)
            if cand is None or score > cand["score"]:
                at, by_term, phase = 0, {}, {}
                for c in cols:
                    w = X[c].shape[1]
                    by_term[c] = float(coef[at]) if w == 1 else float(np.hypot(coef[at], coef[at + 1]))
                    if w == 2:
                        phase[c] = float(np.arctan2(coef[at + 1], coef[at]))    # a sin(x) + b cos(x) = A sin(x + phase)
                    at += w
                cand = {"terms": list(subset), "coef": by_term, "phase_rad": phase, "held_out_r2": float(r2),
                        "score": score}
        if cand is None or cand["held_out_r2"] < best["held_out_r2"] + MIN_GAIN:
            break
        best = cand
    return best


def view_targets(meas_motor, nominal_motor, period_s, ahead_motor=None) -> dict[str, np.ndarray]:
    """What each view regresses (module docstring): ``level`` r(k), and with ``ahead_motor`` ``rate``
    a(k) (NaN for the last ``AHEAD_PERIODS`` steps)."""
    out = {"level": meas_motor - nominal_motor}
    if ahead_motor is not None:
        h = AHEAD_PERIODS
        rate = np.full_like(out["level"], np.nan)
        rate[:-h] = (meas_motor[h:] - ahead_motor[:-h]) / (h * period_s)     # a(k)
        out["rate"] = rate
    return out


def fitted(description: dict, meas_motor, train_ms, creep_kmh, torque_nm, period_s) -> np.ndarray:
    """The description's sum along the run: its intercept plus each term times its coefficient (a
    periodic term as coef x sin(2 pi f t + phase), times the torque for ``torque*periodic``)."""
    terms = library(meas_motor, train_ms, creep_kmh, torque_nm, period_s, description.get("line_hz"))
    y = np.full(meas_motor.shape, float(description.get("intercept") or 0.0))
    for t in description["terms"]:
        col = terms[t["term"]]
        if "phase_rad" in t:      # A sin(x + phase) = A cos(phase) sin(x) + A sin(phase) cos(x): the (sin, cos) columns
            col = col @ np.array([np.cos(t["phase_rad"]), np.sin(t["phase_rad"])])
        y = y + t["coef"] * col
    return y


def describe_residual(meas_motor, nominal_motor, train_ms, creep_kmh, torque_nm, period_s, train_mask,
                      held_mask, ahead_motor=None) -> dict:
    """The sparse description of what the nominal model leaves (module docstring): ``described``
    (bool), ``view`` (level | rate), ``terms`` (each with its coefficient and unit), ``variables`` (what
    they depend on), ``held_out_r2``, and a sentence.  ``ahead_motor[k]``: the nominal model's motor
    speed ``AHEAD_PERIODS`` periods after it was started from the measured state at k
    (``Simulator.ahead``); without it only the level view is tried."""
    targets = view_targets(meas_motor, nominal_motor, period_s, ahead_motor)
    r = targets["level"]
    line_hz = spectral_line(r, train_mask | held_mask, period_s)
    terms = library(meas_motor, train_ms, creep_kmh, torque_nm, period_s, line_hz)
    ok = np.isfinite(meas_motor) & np.isfinite(nominal_motor)
    for v in terms.values():
        ok &= np.isfinite(v).reshape(v.shape[0], -1).all(axis=1)
    views = {}
    for view, target in targets.items():
        sel = ok & np.isfinite(target)
        tr, ho = train_mask & sel, held_mask & sel
        if tr.sum() < 20 or ho.sum() < 20:
            continue
        views[view] = best_subset(np.where(sel, target, 0.0), terms, tr, ho)
    if not views:
        return {"described": False, "why": "too few samples", "terms": [], "variables": [], "held_out_r2": None}
    view, fit = max(views.items(), key=lambda kv: kv[1]["held_out_r2"])
    described = bool(fit["terms"]) and fit["held_out_r2"] >= MIN_R2
    variables = sorted({v for t in fit["terms"] for v in VARIABLES[t]}) if described else []
    what = "motor-speed residual" if view == "level" else "motor acceleration the model lacks (rad/s²)"
    if described:
        parts = " + ".join(_term_text(t, fit, line_hz) for t in fit["terms"])
        depends = [v.replace("_", " ") for v in variables if v != "periodic"]
        said = ([f"depends on {', '.join(depends)}"] if depends else []) + \
            ([f"is periodic at {line_hz:.1f} Hz"] if "periodic" in variables else [])
        sentence = (f"the {what} ≈ {parts} (+ {fit['coef']['1']:.3g}); held-out R² {fit['held_out_r2']:.2f}: "
                    f"the missing term {' and '.join(said)}")
        if view == "level" and fit["terms"] == ["motor_speed"]:
            sentence += f" (reads as a motor-speed sensor gain of {1 + fit['coef']['motor_speed']:.4f})"
    else:
        sentence = (f"no sparse description: no term of the library explains the residual (best held-out R² "
                    f"{fit['held_out_r2']:.2f}, below {MIN_R2})")
    return {"described": described, "view": view,
            "terms": [{"term": t, "coef": fit["coef"][t], "unit": UNITS[t],
                       **({"phase_rad": fit["phase_rad"][t], "frequency_hz": line_hz} if t in fit["phase_rad"] else {})}
                      for t in fit["terms"]],
            "line_hz": line_hz,
            "intercept": fit["coef"].get("1"), "variables": variables, "held_out_r2": fit["held_out_r2"],
            "held_out_r2_by_view": {k: v["held_out_r2"] for k, v in views.items()}, "sentence": sentence}


def _term_text(term: str, fit: dict, line_hz: float | None) -> str:
    coef = fit["coef"][term]
    if term in fit["phase_rad"]:
        wave = f"sin(2π·{line_hz:.2f} Hz·t {fit['phase_rad'][term]:+.2f} rad)"
        return f"{coef:.4g} × {'torque × ' if term.startswith('torque') else ''}{wave}"
    return f"{coef:.4g} × {term.replace('*', ' × ')}"
