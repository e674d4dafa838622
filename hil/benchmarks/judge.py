"""Judging an identification against the truth, per draw and over many: what ``hil bench identify``
reports for every strategy (a helper module of the benchmarks; it registers no command).

Per draw (``judge``):

- ``confirmed``: the strategy confirmed a curve within the run;
- ``correct``: confirmed, and its peak mu within ``TOL_PEAK_MU_PERCENT`` (3 %) and its peak creep within
  ``TOL_PEAK_CREEP_PERCENT`` (10 %) of the true curve's;
- ``before_serious``: confirmed before the true serious stage (the creep passing the true peak creep);
- ``wrong_confirmation``: confirmed but not correct — the failure that matters: a TCU acting on a
  wrong peak;
- coverage: whether the 90 % intervals the strategy published hold the true peak mu and peak creep —
  those at its confirmation, else the last ones it published before the true serious stage (None
  when it published none); an open interval (``IdentificationEvent.peak_open``: its upper ends are
  the strategy's working range, not the data's) never covers;
- ``ci_width_*_percent``: the full width of those intervals, in percent of the truth;
- RT: (t_confirmed − t_fault) / T_det in percent, infinite when not confirmed.

Over draws (``aggregate``): the fractions, coverages, median widths, and RT median and p90 with the
unconfirmed draws counted as infinite (so a median over half unconfirmed draws is infinite, as it
should be: that strategy does not answer in time in most cases).
"""
from __future__ import annotations

import math

import numpy as np

from .. import terminal

TOL_PEAK_MU_PERCENT = 3.0
TOL_PEAK_CREEP_PERCENT = 10.0


def _finite(ci) -> bool:
    return ci is not None and all(x is not None and math.isfinite(x) for x in ci)


def judge(summary: dict, events: list, true_peak_mu: float, true_peak_creep_kmh: float,
          t_serious_s: float | None) -> dict:
    """One draw's verdicts from a run summary (``hil.trace.summarise`` keys) and the strategy's events."""
    confirmed = bool(summary.get("identified"))
    mu_err, creep_err = summary.get("peak_mu_err_percent"), summary.get("peak_creep_err_percent")
    correct = bool(confirmed and mu_err is not None and creep_err is not None
                   and mu_err <= TOL_PEAK_MU_PERCENT and creep_err <= TOL_PEAK_CREEP_PERCENT)
    t_conf = summary.get("t_identified_s")
    before = bool(confirmed and t_serious_s is not None and t_conf is not None and t_conf < t_serious_s)
    # the intervals judged: at the confirmation, else the last published before the serious stage
    judged = None
    for e in events:
        if e.kind == "confirmed" or t_serious_s is None or e.t_s < t_serious_s:
            if _finite(e.peak_mu_ci) and _finite(e.peak_creep_ci):
                judged = e
        if e.kind == "confirmed":
            judged = e if _finite(e.peak_mu_ci) else judged
            break
    out = {"confirmed": confirmed, "correct": correct, "before_serious": before,
           "correct_before_serious": correct and before, "wrong_confirmation": confirmed and not correct,
           "true_peak_mu": true_peak_mu, "true_peak_creep_kmh": true_peak_creep_kmh,
           "rt_percent_or_inf": summary["rt_percent"] if confirmed and summary.get("rt_percent") is not None
           else math.inf,
           "covers_peak_mu": None, "covers_peak_creep": None,
           "ci_width_peak_mu_percent": None, "ci_width_peak_creep_percent": None,
           "judged_ci_kind": None, "judged_ci_open": None}
    if judged is not None:
        (m0, m1), (c0, c1) = judged.peak_mu_ci, judged.peak_creep_ci
        closed = not judged.peak_open
        out.update(covers_peak_mu=bool(closed and m0 <= true_peak_mu <= m1),
                   covers_peak_creep=bool(closed and c0 <= true_peak_creep_kmh <= c1),
                   ci_width_peak_mu_percent=(m1 - m0) / abs(true_peak_mu) * 100.0,
                   ci_width_peak_creep_percent=(c1 - c0) / abs(true_peak_creep_kmh) * 100.0,
                   judged_ci_kind=judged.kind, judged_ci_open=not closed)
    return out


def _fraction(values) -> float | None:
    vals = [bool(v) for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def _median(values) -> float | None:
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.median(vals)) if vals else None


def quantile_or_inf(values, q: float) -> float:
    """Quantile with infinities counted (numpy's percentile turns inf into nan on interpolation)."""
    vals = np.sort(np.asarray(values, float))
    if vals.size == 0:
        return math.nan
    k = int(math.ceil(q / 100.0 * vals.size)) - 1
    return float(vals[min(max(k, 0), vals.size - 1)])


def aggregate(per_draw: list[dict]) -> dict:
    """The figures over draws (``per_draw``: ``judge`` outputs)."""
    rts = [d["rt_percent_or_inf"] for d in per_draw]
    return {
        "draws": len(per_draw),
        "confirmed_fraction": _fraction(d["confirmed"] for d in per_draw),
        "confirmed_before_serious_fraction": _fraction(d["before_serious"] for d in per_draw),
        "correct_fraction": _fraction(d["correct"] for d in per_draw),
        "correct_before_serious_fraction": _fraction(d["correct_before_serious"] for d in per_draw),
        "wrong_confirmation_fraction": _fraction(d["wrong_confirmation"] for d in per_draw),
        "coverage_peak_mu": _fraction(d["covers_peak_mu"] for d in per_draw),
        "coverage_peak_creep": _fraction(d["covers_peak_creep"] for d in per_draw),
        "coverage_draws": sum(d["covers_peak_mu"] is not None for d in per_draw),
        "ci_width_peak_mu_median_percent": _median([d["ci_width_peak_mu_percent"] for d in per_draw]),
        "ci_width_peak_creep_median_percent": _median([d["ci_width_peak_creep_percent"] for d in per_draw]),
        "rt_median_percent": quantile_or_inf(rts, 50),
        "rt_p90_percent": quantile_or_inf(rts, 90),
        **by_law(per_draw),
    }


def by_law(per_draw: list[dict]) -> dict:
    """Wrong confirmations and coverage per law of the true curve (draws carry ``law`` in family
    runs), and how many wrong confirmations the identifier's form itself could not have avoided
    (``form_ok`` False: its best noiseless fit over the same creeps misses the tolerance too)."""
    laws = sorted({d["law"] for d in per_draw if d.get("law")})
    if not laws:
        return {}
    out = {"by_law": {}}
    for law in laws:
        ds = [d for d in per_draw if d.get("law") == law]
        out["by_law"][law] = {"draws": len(ds),
                              "correct_fraction": _fraction(d["correct"] for d in ds),
                              "wrong_confirmation_fraction": _fraction(d["wrong_confirmation"] for d in ds),
                              "coverage_peak_mu": _fraction(d["covers_peak_mu"] for d in ds),
                              "coverage_peak_creep": _fraction(d["covers_peak_creep"] for d in ds)}
    wrong = [d for d in per_draw if d["wrong_confirmation"]]
    out["wrong_confirmations"] = len(wrong)
    out["wrong_where_form_cannot"] = sum(d.get("form_ok") is False for d in wrong)
    out["correct_where_form_cannot"] = sum(d.get("form_ok") is False for d in per_draw if d["correct"])
    return out


COLUMNS = (("strategy", None, "{}"), ("confirmed before serious", "confirmed_before_serious_fraction", "pct"),
           ("correct", "correct_fraction", "pct"), ("correct before serious", "correct_before_serious_fraction", "pct"),
           ("wrong confirmations", "wrong_confirmation_fraction", "pct"),
           ("90 % CI covers peak μ", "coverage_peak_mu", "pct"), ("… peak creep", "coverage_peak_creep", "pct"),
           ("CI width peak μ %", "ci_width_peak_mu_median_percent", ".1f"),
           ("CI width peak creep %", "ci_width_peak_creep_median_percent", ".1f"),
           ("RT median %", "rt_median_percent", ".1f"), ("RT p90 %", "rt_p90_percent", ".1f"),
           ("oracle RT median %", "oracle_rt_median_percent", ".1f"), ("cost p99 µs", "cost_p99_us", ".0f"))
#: what a terminal shows by default (``hil.terminal.WIDTH``): the columns a reader decides on
TERMINAL = (("strategy", None, "{}"), ("correct", "correct_fraction", "pct"),
            ("wrong", "wrong_confirmation_fraction", "pct"), ("unconfirmed", "unconfirmed_fraction", "pct"),
            ("covers μ", "coverage_peak_mu", "pct"), ("covers creep", "coverage_peak_creep", "pct"),
            ("RT median %", "rt_median_percent", ".1f"), ("oracle RT %", "oracle_rt_median_percent", ".1f"))


def _cell(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if fmt == "pct":
        return f"{value * 100:.0f}%"
    if isinstance(value, float) and math.isinf(value):
        return "∞"
    return format(value, fmt)


def table(results: dict, wide: bool, markdown: bool) -> str:
    """``results``: strategy -> aggregate (plus ``oracle_rt_median_percent`` and ``cost_p99_us``): every
    column as markdown or, with ``wide``, aligned; else the ``TERMINAL`` columns."""
    cols = COLUMNS if wide or markdown else TERMINAL
    rows = [[name] + [_cell(_value(r, key), fmt) for _, key, fmt in cols[1:]] for name, r in results.items()]
    head = [c[0] for c in cols]
    if markdown:
        return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
                         + ["| " + " | ".join(r) + " |" for r in rows])
    return terminal.columns(head, rows)


def unconfirmed_fraction(r: dict) -> float | None:
    """The draws not confirmed within the run, from an aggregate (None when unknown)."""
    confirmed = r.get("confirmed_fraction")
    return None if confirmed is None else 1.0 - confirmed


def _value(r: dict, key: str):
    return unconfirmed_fraction(r) if key == "unconfirmed_fraction" else r.get(key)
