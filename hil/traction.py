"""Closed-loop traction figures of a run, against the truth no TCU sees (shared/spec/control-and-verdicts.md).

``TruthTrack`` keeps, per exchange period, the plant's true state and the truth of the rail at that time
(the current curve's peak mu and peak creep, plant/rail.py) beside the driver's demand; ``metrics``
turns such arrays (from a run, or read back from a log's ``/plant/state`` and ``/plant/rail``) into:

    F_x = mu N,   F_d = mu_d N,   F_cap = min(F_d, mu_peak N)                  N: the axle's normal force
    eta      = sum(F_x) / sum(F_cap)                                          adhesion utilisation, whole run
    eta_low  = the same over the steps where mu_d > mu_peak, and the ``AFTER_CHANGE_S`` after each rail change
    macro-slip: |v_s| > 2 v_peak (either direction: a wheel sliding backwards under a torque of the wrong sign
        too) for longer than ``MACRO_SLIP_MIN_S`` in a row: the time in such episodes, their count
    reaction (per drop: a rail change to a lower peak that the demand exceeds, judged at the segment's end): from the first step the true creep exceeds
        the current peak creep to the first step the applied torque is below ``REDUCED_FRACTION`` of the demand,
        both searched from the drop's start (negative: the torque was cut before the creep crossed the peak;
        a creep that never crossed it: from the drop's start, the detection latency)
    recovery (per rail change): from the change's start to the first step from which F_x >= 0.9 F_cap holds
        for ``RECOVERED_HOLD_S`` (or to the segment's end)
    ripple: std / mean of the applied torque in each steady stretch (a rail segment, from ``AFTER_CHANGE_S``
        after its change, where the demand does not move), in percent; the largest over stretches
    traction energy = sum(F_x v_t T), distance = sum(v_t T)
    per drop (``drop_figures``): the identification the TCU confirmed after it (its first confirmed event
        between the drop and the next change), RT = (t_identified - t_drop) / T_det with T_det the time from the
        drop to the first step the creep crossed the current peak creep (none: no RT, the controller kept the
        wheel on the stable side), and the confirmed curve's peak errors against the rail's true peak then

Why per step and from the plant's truth: the figures must hold for any TCU on the bus (the built-in one,
an external one), so they are computed from what the plant did, never from what a TCU reports.
"""
from __future__ import annotations

import math

import numpy as np

#: eta_low also covers this long after each rail change (where controllers differ)
AFTER_CHANGE_S = 1.0
#: macro-slip: |creep| above MACRO_SLIP_FACTOR x the current peak creep for longer than this
MACRO_SLIP_FACTOR = 2.0
MACRO_SLIP_MIN_S = 0.05
#: a torque below this fraction of the demand counts as a reduction (reaction time)
REDUCED_FRACTION = 0.98
#: recovered: F_x >= RECOVERED_FRACTION F_cap held this long
RECOVERED_FRACTION = 0.9
RECOVERED_HOLD_S = 0.2

SUMMARY_KEYS = ("adhesion_utilisation", "adhesion_utilisation_low", "macro_slip_s", "macro_slip_count",
                "reaction_ms", "recovery_s", "torque_ripple_percent", "traction_energy_mj", "distance_m")


def response_text(reaction_ms, recovery_s) -> str:
    """Reaction and recovery as the summaries print them ("n/a" where a run has no drop or rail
    change), saying what a negative reaction means: the torque was cut before the creep passed the
    current peak creep."""
    def given(x):
        return x is not None and math.isfinite(x)
    reaction = "reaction n/a" if not given(reaction_ms) else f"reaction {reaction_ms:.1f} ms" + (
        " (torque cut before the peak)" if reaction_ms < 0 else "")
    return reaction + (f", recovery {recovery_s:.3f} s" if given(recovery_s) else ", recovery n/a")


class TruthTrack:
    """Per step: the true state, the rail's truth and the demand (module docstring)."""

    def __init__(self, scenario):
        v = scenario.vehicle
        self.scenario = scenario
        self.torque_per_mu_nm = v.torque_per_mu_nm
        self.normal_force_n = v.normal_force_n
        self.period_s = scenario.run.exchange_period_s
        self.rail = scenario.rail
        self._demand = scenario.control.demand
        self._constant_nm = None if self._demand is not None else scenario.identifier_settings().torque_demand_nm
        if self.rail is None:
            self._peaks = (scenario.normal_curve.peak(), scenario.fault_curve.peak())
        self._rows: list[tuple] = []        # per step, in COLUMNS order

    #: the per-step figures kept, in the order of a kept row
    COLUMNS = ("t_s", "creep_speed_kmh", "mu", "torque_nm", "train_speed_ms", "demand_mu", "peak_mu", "peak_creep_kmh",
               "segment")

    @property
    def cols(self) -> dict[str, np.ndarray]:
        """Each of ``COLUMNS`` over the steps kept, as an array."""
        table = np.array(self._rows, float).reshape(-1, len(self.COLUMNS))
        return {k: table[:, i] for i, k in enumerate(self.COLUMNS)}

    def demand_torque_nm(self, t_s: float) -> float:
        return self._constant_nm if self._demand is None else self._demand.at(t_s) * self.torque_per_mu_nm

    def truth(self, t_s: float, train_speed_ms: float, cleaned=()) -> tuple[float, float, int]:
        """(peak mu, peak creep km/h, segment) of the rail at ``t_s``."""
        if self.rail is None:
            after = t_s >= self.scenario.run.fault_time_s
            v, mu = self._peaks[after]
            return mu, v, int(after)
        v, mu = self.rail.peak(t_s, train_speed_ms, cleaned)
        return mu, v, self.rail.index_at(t_s)

    def add(self, state, cleaned=()) -> tuple[float, float, float, int]:
        """Keep one step; returns (peak mu, peak creep, demand mu, segment) for the log."""
        peak_mu, peak_creep, segment = self.truth(state.t_s, state.train_speed_ms, cleaned)
        demand_mu = self.demand_torque_nm(state.t_s) / self.torque_per_mu_nm
        self._rows.append((state.t_s, state.creep_speed_kmh, state.mu, state.torque_nm, state.train_speed_ms,
                           demand_mu, peak_mu, peak_creep, segment))
        return peak_mu, peak_creep, demand_mu, segment

    def changes_s(self) -> tuple[float, ...]:
        """Where the rail changes: each segment's start after the first (the paper's runs: the fault)."""
        return self.rail.transitions_s if self.rail is not None else (self.scenario.run.fault_time_s,)

    def metrics(self, events=(), estimates=None) -> dict:
        """The run's figures (module docstring); ``events``: the TCU's identification events, for the per-drop
        identification figures (``drop_identification``); ``estimates``: the built-in TCU's peak estimates (a
        trace of them), for ``peak_estimate`` per rail change (``estimate_figures``; None: an external TCU)."""
        c = self.cols
        out = metrics(c, self.changes_s(), self.period_s, self.normal_force_n, self.torque_per_mu_nm)
        out["drop_identification"] = drop_figures(c, self.changes_s(), events)
        if estimates is not None and self.rail is not None:
            fig = estimate_figures(c, self.changes_s(), estimates, every=1)
            out["peak_estimate"] = [{"change_s": r["t_s"], "lead_time_ms": r["lead_time_ms"],
                                     **(r["peak_estimate"] or {})} for r in fig["per_change"]]
        return out


def drop_figures(c: dict, changes_s, events) -> list[dict]:
    """Per drop (module docstring): the identification figures, from per-step arrays ``c`` and the TCU's
    identification ``events`` (each with ``t_s``, ``kind``, ``params``)."""
    from identifier.curve import peak
    from identifier.metrics import rt_percent

    t, creep, p_mu, p_creep, d_mu = c["t_s"], c["creep_speed_kmh"], c["peak_mu"], c["peak_creep_kmh"], c["demand_mu"]
    out = []
    changes = [float(x) for x in changes_s if t.size and t[0] <= x <= t[-1]]
    for x, end in zip(changes, changes[1:] + [math.inf]):
        seg = np.flatnonzero((t >= x) & (t < end))
        if seg.size == 0 or not (p_mu[seg[-1]] < p_mu[max(seg[0] - 1, 0)] and d_mu[seg[-1]] > p_mu[seg[-1]]):
            continue
        crossed = seg[creep[seg] > p_creep[seg]]
        t_det = float(t[crossed[0]] - x) if crossed.size else math.nan
        conf = next((e for e in events if e.kind == "confirmed" and x <= e.t_s < end), None)
        row = {"t_s": x, "t_det_ms": t_det * 1e3 if math.isfinite(t_det) else None,
               "t_identified_s": None, "rt_percent": None, "peak_mu_err_percent": None,
               "peak_creep_err_percent": None, "interval_holds_truth": None}
        if conf is not None and len(conf.params) >= 3:
            i = int(np.clip(np.searchsorted(t, conf.t_s), 0, t.size - 1))
            v_hat, mu_hat = peak(np.asarray(conf.params, float))
            rt = rt_percent(conf.t_s, x, t_det)
            row.update({"t_identified_s": conf.t_s, "rt_percent": rt if math.isfinite(rt) else None,
                        "peak_mu_err_percent": 100.0 * abs(mu_hat - p_mu[i]) / p_mu[i],
                        "peak_creep_err_percent": 100.0 * abs(v_hat - p_creep[i]) / p_creep[i]})
            mu_ci, creep_ci = getattr(conf, "peak_mu_ci", None), getattr(conf, "peak_creep_ci", None)
            if mu_ci is not None and creep_ci is not None and all(map(math.isfinite, (*mu_ci, *creep_ci))):
                # an open interval never holds the truth (its upper end is the TCU's range)
                row["interval_holds_truth"] = bool(not getattr(conf, "peak_open", False)
                                                   and mu_ci[0] <= p_mu[i] <= mu_ci[1]
                                                   and creep_ci[0] <= p_creep[i] <= creep_ci[1])
        out.append(row)
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index pairs of the True stretches of ``mask``."""
    m = np.concatenate(([False], mask, [False])).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def _median(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.median(xs)) if xs else None


def metrics(c: dict, changes_s, period_s: float, normal_force_n: float, torque_per_mu_nm: float) -> dict:
    """The module docstring's figures from per-step arrays ``c`` (keys as ``TruthTrack.cols``)."""
    t, creep, mu, torque = c["t_s"], c["creep_speed_kmh"], c["mu"], c["torque_nm"]
    d_mu, p_mu, p_creep, v_t = c["demand_mu"], c["peak_mu"], c["peak_creep_kmh"], c["train_speed_ms"]
    n = t.size
    if n == 0:
        return {k: None for k in SUMMARY_KEYS} | {"drops": 0}
    f_x = mu * normal_force_n
    f_cap = np.minimum(d_mu, p_mu) * normal_force_n
    eta = float(f_x.sum() / f_cap.sum()) if f_cap.sum() > 0 else None
    low = d_mu > p_mu
    changes = [float(x) for x in changes_s if t[0] <= x <= t[-1]]
    for x in changes:
        low |= (t >= x) & (t < x + AFTER_CHANGE_S)
    eta_low = float(f_x[low].sum() / f_cap[low].sum()) if low.any() and f_cap[low].sum() > 0 else None

    min_steps = int(round(MACRO_SLIP_MIN_S / period_s))
    episodes = [(a, b) for a, b in _runs(np.abs(creep) > MACRO_SLIP_FACTOR * p_creep) if b - a > min_steps]
    macro_s = sum(b - a for a, b in episodes) * period_s

    ends = changes[1:] + [t[-1] + period_s]
    demand_nm = d_mu * torque_per_mu_nm
    reactions, recoveries, drops = [], [], 0
    for x, end in zip(changes, ends):
        seg = np.flatnonzero((t >= x) & (t < end))
        if seg.size == 0:
            continue
        settled = seg[-1]
        before = max(seg[0] - 1, 0)
        if p_mu[settled] < p_mu[before] and d_mu[settled] > p_mu[settled]:   # a drop: the demand exceeds the new rail
            drops += 1
            crossed = seg[creep[seg] > p_creep[seg]]
            reduced = seg[torque[seg] < REDUCED_FRACTION * demand_nm[seg]]
            if reduced.size:
                reactions.append((t[reduced[0]] - (t[crossed[0]] if crossed.size else x)) * 1e3)
        hold = int(round(RECOVERED_HOLD_S / period_s))
        ok = f_x[seg] >= RECOVERED_FRACTION * f_cap[seg]
        for j in range(seg.size):
            if ok[j:j + hold].all():
                recoveries.append(t[seg[j]] - x)
                break
    ripples = []
    for x, end in zip([t[0]] + changes, changes + [t[-1] + period_s]):
        steady = (t >= (x + AFTER_CHANGE_S if x > t[0] else x)) & (t < end)
        steady &= np.concatenate(([True], np.diff(d_mu) == 0))
        for a, b in _runs(steady):
            if b - a >= 10 and torque[a:b].mean() > 0:
                ripples.append(100.0 * float(torque[a:b].std() / torque[a:b].mean()))
    return {"adhesion_utilisation": eta, "adhesion_utilisation_low": eta_low, "macro_slip_s": macro_s,
            "macro_slip_count": len(episodes), "reaction_ms": _median(reactions), "recovery_s": _median(recoveries),
            "torque_ripple_percent": max(ripples) if ripples else None,
            "traction_energy_mj": float((f_x * v_t).sum() * period_s / 1e6), "distance_m": float(v_t.sum() * period_s),
            "drops": drops}


#: the lead time's target window and its accuracy: an estimate whose interval holds the true peak creep and whose
#: centre lies within LEAD_ACCURACY of it
LEAD_ACCURACY = 0.10


def estimate_figures(c: dict, changes_s, estimates, every: int = 10) -> dict:
    """The TCU's predictive peak estimates (identifier/peak_estimate.py ``PeakEstimate``, one per period) against the
    rail's truth at their time, from per-step arrays ``c`` (``TruthTrack.cols``):

    - ``coverage_peak_creep``, ``coverage_peak_mu``: the fraction of estimates (every ``every``-th) whose 90 %
      interval holds the true current peak creep (peak mu);
    - ``per_change``: for each change of rail, ``lead_time_ms``, from the change's start to the first estimate
      whose peak-creep interval holds the true peak creep then and whose centre is within ``LEAD_ACCURACY`` of it
      (None: none before the next change), and the estimate published 100 ms after the change
      (``peak_estimate``: centre and interval, and the truth then)."""
    t, p_mu, p_creep = c["t_s"], c["peak_mu"], c["peak_creep_kmh"]
    if not estimates or t.size == 0:
        return {"coverage_peak_creep": None, "coverage_peak_mu": None, "estimates": 0, "per_change": []}
    steps = np.array([e.step for e in estimates])
    period = float(np.median(np.diff(t))) if t.size > 1 else 1e-3
    idx = np.clip(np.searchsorted(t, steps * period - 1e-9), 0, t.size - 1)
    lo = np.array([e.peak_creep_ci[0] for e in estimates])
    hi = np.array([e.peak_creep_ci[1] for e in estimates])
    mid = np.array([e.peak_creep_kmh for e in estimates])
    mlo = np.array([e.peak_mu_ci[0] for e in estimates])
    mhi = np.array([e.peak_mu_ci[1] for e in estimates])
    truth_v, truth_mu = p_creep[idx], p_mu[idx]
    holds = (lo <= truth_v) & (truth_v <= hi)
    good = holds & (np.abs(mid - truth_v) <= LEAD_ACCURACY * truth_v)
    sub = slice(None, None, max(int(every), 1))
    out = {"coverage_peak_creep": float(holds[sub].mean()),
           "coverage_peak_mu": float(((mlo <= truth_mu) & (truth_mu <= mhi))[sub].mean()),
           "estimates": int(len(estimates)), "per_change": []}
    changes = [float(x) for x in changes_s if t[0] <= x <= t[-1]]
    times = steps * period
    for x, end in zip(changes, changes[1:] + [math.inf]):
        inside = np.flatnonzero((times >= x - 1e-9) & (times < end) & good)
        j = int(np.searchsorted(times, x + 0.1 - 1e-9))
        row = {"t_s": x, "lead_time_ms": float((times[inside[0]] - x) * 1e3) if inside.size else None,
               "peak_estimate": None}
        if j < len(estimates) and times[j] < end:
            e = estimates[j]
            row["peak_estimate"] = {"t_s": float(times[j]), "peak_creep_kmh": e.peak_creep_kmh,
                                    "peak_creep_ci": list(e.peak_creep_ci), "peak_mu": e.peak_mu,
                                    "peak_mu_ci": list(e.peak_mu_ci), "since_s": e.since_step * period,
                                    "true_peak_creep_kmh": float(truth_v[j]), "true_peak_mu": float(truth_mu[j])}
        out["per_change"].append(row)
    return out
