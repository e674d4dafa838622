"""When no candidate explains the gap, describe it: a sparse regression of what the nominal model
leaves on a small library of terms says what the missing term depends on.

Two views of the motor-speed residual r(k) = y_meas(k) - y_nominal(k) over the analysis window:

    level:  r(k)                        = sum_i xi_i theta_i(k)      a sensor-type term (``motor speed x 0.01``
                                                                     reads as a tachometer gain of 1.01)
    rate:   (r(k+1) - r(k)) / dt        = sum_i xi_i theta_i(k)      a dynamics-type term (an acceleration the
                                                                     model lacks, e.g. a torque it does not apply)

with the library theta = {1, motor speed, train speed, creep speed, creep rate, torque command}, all
measured.  (Products such as motor speed x torque fitted a tachometer gain as well as motor speed
alone did, and then named two variables where one is the answer: ``TERMS`` leaves them out.)  The sparse fit is a best subset of
at most ``MAX_TERMS`` terms, chosen on the training blocks and judged on the held-out blocks (the
diagnosis' own split): a term is added only when it raises the held-out R^2 by ``MIN_GAIN``.  This is
SINDy's idea (Brunton, Proctor and Kutz, PNAS 2016) with an exhaustive subset in place of sequential
thresholding, which a library of ten terms affords.  The view with the higher held-out R^2 is
reported; below ``MIN_R2`` the answer is "no sparse description": the missing term is not in the
library (a 60 Hz torque ripple is not), which is said rather than a term being forced.
"""
from __future__ import annotations

from itertools import combinations

import numpy as np

#: the most terms a description uses
MAX_TERMS = 2
#: the held-out R^2 an added term must add
MIN_GAIN = 0.05
#: the held-out R^2 below which there is no description
MIN_R2 = 0.3
#: what each term depends on (the variables a description names)
VARIABLES = {"1": (), "motor_speed": ("motor_speed",), "train_speed": ("train_speed",),
             "creep_speed": ("creep_speed",), "creep_rate": ("creep_speed",), "torque": ("torque",),
             "motor_speed*torque": ("motor_speed", "torque"), "creep_speed*torque": ("creep_speed", "torque")}
TERMS = ("1", "motor_speed", "train_speed", "creep_speed", "creep_rate", "torque")
UNITS = {"1": "", "motor_speed": "rad/s", "train_speed": "m/s", "creep_speed": "km/h", "creep_rate": "km/h/s",
         "torque": "N·m", "motor_speed*torque": "rad/s·N·m", "creep_speed*torque": "km/h·N·m"}


def library(motor_rad_s, train_ms, creep_kmh, torque_nm, period_s) -> dict[str, np.ndarray]:
    """The library's terms along the measured run."""
    creep_rate = np.gradient(creep_kmh, period_s)
    out = {"1": np.ones_like(motor_rad_s), "motor_speed": motor_rad_s, "train_speed": train_ms,
           "creep_speed": creep_kmh, "creep_rate": creep_rate, "torque": torque_nm,
           "motor_speed*torque": motor_rad_s * torque_nm, "creep_speed*torque": creep_kmh * torque_nm}
    return {k: v for k, v in out.items() if k in TERMS}


def _r2(y, yhat) -> float:
    ss = float(np.sum((y - y.mean()) ** 2))
    return 1.0 - float(np.sum((y - yhat) ** 2)) / ss if ss > 0 else 0.0


def best_subset(target, terms: dict, train, held) -> dict:
    """The subset of at most MAX_TERMS terms (the constant always in) with the best held-out R^2,
    grown one term at a time only while each adds MIN_GAIN."""
    names = [n for n in terms if n != "1"]
    X = {n: terms[n] for n in terms}
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
            if cand is None or r2 > cand["held_out_r2"]:
                cand = {"terms": list(subset), "coef": {c: float(v) for c, v in zip(cols, coef)},
                        "held_out_r2": float(r2)}
        if cand is None or cand["held_out_r2"] < best["held_out_r2"] + MIN_GAIN:
            break
        best = cand
    return best


def describe_residual(meas_motor, nominal_motor, train_ms, creep_kmh, torque_nm, period_s, train_mask,
                      held_mask) -> dict:
    """The sparse description of the motor-speed residual (module docstring): ``described`` (bool),
    ``view`` (level | rate), ``terms`` (each with its coefficient and unit), ``variables`` (what they
    depend on), ``held_out_r2``, and a sentence."""
    terms = library(meas_motor, train_ms, creep_kmh, torque_nm, period_s)
    ok = np.isfinite(meas_motor) & np.isfinite(nominal_motor)
    for v in terms.values():
        ok &= np.isfinite(v)
    r = meas_motor - nominal_motor
    rate = np.full_like(r, np.nan)
    rate[:-1] = np.diff(r) / period_s
    views = {}
    for view, target in (("level", r), ("rate", rate)):
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
    what = "motor-speed residual" if view == "level" else "rate of the motor-speed residual (rad/s²)"
    if described:
        parts = " + ".join(f"{fit['coef'][t]:.4g} × {t.replace('*', ' × ')}" for t in fit["terms"])
        sentence = (f"the {what} ≈ {parts} (+ {fit['coef']['1']:.3g}); held-out R² {fit['held_out_r2']:.2f}: "
                    f"the missing term depends on {', '.join(v.replace('_', ' ') for v in variables)}")
        if view == "level" and fit["terms"] == ["motor_speed"]:
            sentence += f" (reads as a motor-speed sensor gain of {1 + fit['coef']['motor_speed']:.4f})"
    else:
        sentence = (f"no sparse description: no term of the library explains the residual (best held-out R² "
                    f"{fit['held_out_r2']:.2f}, below {MIN_R2})")
    return {"described": described, "view": view,
            "terms": [{"term": t, "coef": fit["coef"][t], "unit": UNITS[t]} for t in fit["terms"]],
            "intercept": fit["coef"].get("1"), "variables": variables, "held_out_r2": fit["held_out_r2"],
            "held_out_r2_by_view": {k: v["held_out_r2"] for k, v in views.items()}, "sentence": sentence}
