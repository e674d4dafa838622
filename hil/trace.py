"""A run's trace and its summary, computed in one place for ``hil run``, ``hil replay`` and the benches.

``Trace`` collects what a run leaves to judge it by: the true stages (``StageTracker``), the TCU's
identification events, the samples its strategy used (as the TCU reported them), its slip detection
step, and — in ONE window, ``0 <= step - fault_step <= LAG_WINDOW_S / period`` — the true mu and the
observer's mu^ by step, for the observer-lag figure.  ``Trace.summary`` gives the ``hil run --json``
object: stages, RT, fit metrics against the samples (the paper's), peak errors against the true
curve, the observer lag.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from identifier.metrics import against_truth, fit_metrics, intervals_hold_truth, rt_percent
from plant import StageTracker

#: how long after the fault the true mu and mu^ are kept for the observer-lag figure
LAG_WINDOW_S = 0.3


class Trace:
    """Feed it as the run goes (``plant``, ``observer``, ``event``, ``sample``, ``detected``), then
    ask for ``summary``.  Steps index exchange periods; times are ``step * period``."""

    def __init__(self, scenario):
        self.scenario = scenario
        self.period_s = scenario.run.exchange_period_s
        self.fault_step = int(round(scenario.run.fault_time_s / self.period_s))
        self._window_steps = int(round(LAG_WINDOW_S / self.period_s))
        self.tracker = StageTracker(scenario.run.fault_time_s, scenario.fault_curve.peak()[0])
        self.events: list = []
        self._pending: list = []          # results waiting for their interval frame
        self.samples_v: list[float] = []
        self.samples_mu: list[float] = []
        self.detected_step: int | None = None
        #: the TCU's peak estimates as its TcuEstimate frames brought them (``hil.bus.frames.EstimateReport``)
        self.estimates: list = []
        self._truth_mu: dict[int, float] = {}
        self._observer_mu: dict[int, float] = {}

    def _in_window(self, step: int) -> bool:
        return 0 <= step - self.fault_step <= self._window_steps

    def plant(self, step: int, t_s: float, creep_speed_kmh: float, mu: float) -> str:
        """The true state at ``step``; returns its stage (normal, early, serious)."""
        stage = self.tracker.update(t_s, creep_speed_kmh)
        if self._in_window(step):
            self._truth_mu[step] = mu
        return stage

    def observer(self, obs) -> None:
        if obs is not None and self._in_window(obs.step):
            self._observer_mu[obs.step] = obs.mu_hat

    def result(self, e) -> None:
        """An identification event as it arrives; final once ``settle`` passes its step (its interval,
        sent right after it, may still come)."""
        self._pending.append(e)

    def interval(self, r) -> bool:
        """Attach an ``IntervalReport`` to its pending result; False when none matches."""
        for i, e in enumerate(self._pending):
            if (e.step, e.correction, e.kind) == (r.step, r.correction, r.kind):
                self._pending[i] = dataclasses.replace(e, peak_mu_ci=r.peak_mu_ci, peak_creep_ci=r.peak_creep_ci,
                                                       peak_open=r.peak_open, samples_from_s=r.samples_from_s,
                                                       samples_to_s=r.samples_to_s)
                return True
        return False

    def estimate(self, r) -> None:
        """A peak estimate of the TCU's (``EstimateReport``), in the order they came."""
        self.estimates.append(r)

    def settle(self, upto_step: int | None = None) -> list:
        """The pending results of steps up to ``upto_step`` (all: None), now final: moved to ``events``
        and returned (for the log)."""
        done = [e for e in self._pending if upto_step is None or e.step <= upto_step]
        self._pending = [e for e in self._pending if not (upto_step is None or e.step <= upto_step)]
        self.events.extend(done)
        return done

    def sample(self, creep_speed_kmh: float, mu_hat: float) -> None:
        self.samples_v.append(creep_speed_kmh)
        self.samples_mu.append(mu_hat)

    def detected(self, step: int | None) -> None:
        if step is not None and self.detected_step is None:
            self.detected_step = step

    def observer_lag_ms(self) -> float | None:
        """``observer_lag_ms`` over the window (up to the serious stage); None when a step of the
        truth window has no mu^ (the TCU's side of the run is incomplete, e.g. a cut log)."""
        steps = sorted(self._truth_mu)
        if not steps or any(s not in self._observer_mu for s in steps):
            return None
        t = [s * self.period_s for s in steps]
        return observer_lag_ms(t, [self._truth_mu[s] for s in steps], [self._observer_mu[s] for s in steps],
                               self.scenario.run.fault_time_s,
                               self.tracker.serious_time_s or self.scenario.run.duration_s, self.period_s)

    def summary(self, *, strategy: str, seed: int, bus: str, mcap_path=None, extra=None) -> dict:
        self.settle()
        det = self.detected_step
        return summarise(scenario=self.scenario, strategy=strategy, seed=seed, bus=bus, tracker=self.tracker,
                         events=self.events, samples_v=np.asarray(self.samples_v, float),
                         samples_mu=np.asarray(self.samples_mu, float),
                         t_detected_s=None if det is None else det * self.period_s, mcap_path=mcap_path,
                         extra={"observer_lag_ms": self.observer_lag_ms(), **(extra or {})})


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
    last = confirmed or (events[-1] if events else None)
    truth = scenario.fault_curve
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
        # the TCU's own 90 % intervals of the peak for that curve ([lo, hi]; null when it gave none)
        "peak_mu_ci": _interval(last.peak_mu_ci) if last else None,
        "peak_creep_ci": _interval(last.peak_creep_ci) if last else None,
        # true: those intervals are open, their upper ends the TCU's working range (they never count as covering)
        "peak_interval_open": bool(last.peak_open) if last and _interval(last.peak_creep_ci) else None,
        "unconfirmed": bool(events) and events[-1].kind == "unconfirmed",
        "true_params": list(truth.params) if hasattr(truth, "params") else None,
        "corrections": len(corrections),
        "samples": len(samples_v),
        "mcap": str(mcap_path) if mcap_path else None,
    }
    if last is not None:
        theta = np.asarray(last.params)
        out.update(fit_metrics(samples_v, samples_mu, theta))
        out.update(against_truth(theta, truth))
        out["peak_ci_holds_truth"] = intervals_hold_truth(out["peak_mu_ci"], out["peak_creep_ci"],
                                                          bool(out["peak_interval_open"]), truth)
    else:
        out.update({k: None for k in ("mse", "rmse", "mae", "r2", *TRUTH_KEYS)})
    out.update(extra or {})
    return clean(out)


def _interval(ci) -> list[float] | None:
    return [float(x) for x in ci] if all(math.isfinite(x) for x in ci) else None


TRUTH_KEYS = ("peak_mu", "peak_creep_kmh", "peak_mu_err_percent", "peak_creep_err_percent", "curve_rmse_vs_truth",
              "r2_vs_truth", "r2_vs_truth_to_peak", "peak_ci_holds_truth")


