"""The checks: each a function that builds a ``Check`` (what to check), which judged over a run
(``check(run)``) gives a ``Result``; ``require`` judges several and fails with every failed one.

Every check judges samples inside a *window*: the whole run, or one relative to an event of the run
(``during=("fault", 0.0, 0.3)``: from the fault to 300 ms after it; ``during="fault"``: from the fault
to the end; ``hil.checks.run`` lists the events).  A check may be *masked* by a validity signal
(``valid="TcuStatus.ObserverValid"``): only samples where it holds a non-zero value count.

Per sample i of the window, with hold time dt_i (to the next sample; the last takes the median):

    margin_i = min(v_i - lo, hi - v_i)          (an absent bound is +inf; NaN counts as a violation)
    violated_i = margin_i < 0
    margin   = min_i margin_i                   (signed: > 0 inside the band, < 0 the worst excess)
    time in violation = sum of dt_i over violated samples

``first`` is the first violated sample (t, v), ``worst`` the sample of least margin.  A window with no
samples, or an event that did not happen, fails: a check that found nothing to judge never passes.

Timing checks (``cycle_time``, ``responds``) measure real-time runs in receive wall time; a lockstep
run's wall time says nothing about the TCU (the plant waits for it), so there they count exchange
steps (``t_s``, the simulated time of the step) and their result says so (``note``).
"""
from __future__ import annotations

import math
import operator
import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .run import Run, as_run

_OPS = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge, "==": operator.eq,
        "!=": operator.ne}
_CONDITION = re.compile(r"^\s*(\S+?)\s*(<=|>=|==|!=|<|>)\s*([-+0-9.eE]+|inf|-inf)\s*$")


@dataclass
class Result:
    """What one check found.  ``first`` and ``worst`` are (t_s, value) or None; ``margin`` is signed
    (negative: by how much the limit was broken); ``violation_s`` the time in violation."""
    name: str
    kind: str
    signal: str
    unit: str
    window: str
    limit: str                                        # the requirement: "[0.02, 0.3]", "<= 50 ms" ...
    passed: bool
    verb: str = "outside"                             # what a failure did to the limit
    req: str = ""
    first: tuple | None = None
    worst: tuple | None = None
    violation_s: float = 0.0
    margin: float | None = None
    margin_unit: str = ""                             # the unit of margin when not the signal's (ms)
    samples: int = 0
    note: str = ""
    reason: str = ""                                  # why it failed when no sample says it (no data ...)
    window_s: tuple | None = None                     # (t0, t1) in s; None: the whole run
    lo: float | None = None
    hi: float | None = None
    plot: dict = field(default_factory=dict, repr=False)   # t, v (and mask) for the failure's figure

    def line(self) -> str:
        """One line: the failure as an engineer reads it, or the pass with its margin."""
        req = f"[{self.req}] " if self.req else ""
        # the requirement, the check's name and the signal it judged (when the name does not say it)
        head = f"{req}{self.name}" + (f" ({self.signal})" if self.signal and self.signal not in self.name else "")
        if self.passed:
            margin = "" if self.margin is None else f", margin {_num(self.margin)}{_u(self.margin_unit or self.unit)}"
            return (f"{head} {self.limit} {self.window}: passed ({self.samples} sample{'s' * (self.samples != 1)}"
                    f"{margin})" + _note(self.note))
        if self.reason:
            return " ".join(p for p in (head, self.verb, self.limit, self.window) if p) + f": {self.reason}" \
                + _note(self.note)
        if self.first is not None and self.first[0] is None:          # one value (a summary's)
            return f"{head} = {_num(self.first[1])}{_u(self.unit)} {self.verb} {self.limit} {self.window}"
        parts = []
        if self.first is not None:
            parts.append(f"first {_t(self.first[0])} ({self._value(self.first[1])})")
        if self.worst is not None:
            parts.append(f"worst {self._value(self.worst[1])} at {_t(self.worst[0])}")
        if self.violation_s:
            parts.append(f"{_dur(self.violation_s)} in violation")
        return f"{head} {self.verb} {self.limit} {self.window}: " + ", ".join(parts) + _note(self.note)

    def _value(self, v) -> str:
        return _num(v) + ("" if v == math.inf else _u(self.unit))



def _num(x) -> str:
    if x == math.inf:
        return "never"
    if x is None:
        return "none"
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return f"{x:.4g}" if isinstance(x, float) else str(x)


def _u(unit: str) -> str:
    return f" {unit}" if unit else ""


def _t(t: float) -> str:
    return f"{t:.3f} s"


def _dur(s: float) -> str:
    return f"{s * 1e3:.0f} ms" if s < 10 else f"{s:.2f} s"


def _note(note: str) -> str:
    return f" ({note})" if note else ""


def _bounds(lo, hi) -> str:
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    return f"[{lo_s}, {hi_s}]"


class Check:
    """What to check; ``check(run)`` judges it over a run (a ``Run`` or a log's path)."""
    kind = ""

    def __init__(self, name: str | None, req: str | None):
        self._name, self.req = name, req or ""
        self.where = ""                     # where it was written (a checks file and table), for errors

    @property
    def name(self) -> str:
        return self._name or self.default_name()

    def default_name(self) -> str:
        raise NotImplementedError

    def __call__(self, run) -> Result:
        return self.judge(as_run(run))

    def judge(self, run: Run) -> Result:
        raise NotImplementedError

    def fields(self) -> dict:
        """The check's fields as a ``[[check]]`` table has them (``hil.checks.spec``): what ``dump_checks``
        writes so that ``hil check`` judges a check written in Python the same."""
        raise NotImplementedError

    def table(self) -> dict:
        """``fields`` with the kind, name and requirement: a ``[[check]]`` table (None values left out)."""
        out = {"kind": self.kind, **({"name": self._name} if self._name else {}),
               **({"req": self.req} if self.req else {}), **self.fields()}
        return {k: v for k, v in out.items() if v is not None}

    def __repr__(self) -> str:
        return f"<{self.kind} {self.name}>"


# -- windows ---------------------------------------------------------------------------------------------
def parse_window(during) -> tuple | None:
    """``during`` -> (event, start offset s, end offset s or None); None for the whole run."""
    if during is None:
        return None
    if isinstance(during, str):
        return (during, 0.0, None)
    if isinstance(during, (tuple, list)) and len(during) in (2, 3) and isinstance(during[0], str):
        a = float(during[1])
        b = None if len(during) == 2 or during[2] is None else float(during[2])
        if b is not None and b < a:
            raise ConfigError(f"during {list(during)!r}: the window ends before it starts")
        return (during[0], a, b)
    raise ConfigError(f"during {during!r}: expected an event name or (event, start_s, end_s), e.g. ('fault', 0.0, 0.3)")


def window_field(window):
    """A parsed window back as a checks file writes it: None, ``"event"`` or ``[event, start_s, end_s]``."""
    if window is None:
        return None
    event, a, b = window
    if b is None:
        return event if a == 0 else [event, a]
    return [event, a, b]


def window_text(window) -> str:
    if window is None:
        return "over the whole run"
    event, a, b = window
    if event == "start":
        return f"during {a:g}..{b:g} s" if b is not None else f"from {a:g} s on"
    a_ms = f"{a * 1e3:+.0f}"
    if b is None:
        return f"from {event}{a_ms} ms on"
    return f"during {event}{a_ms}..{b * 1e3:.0f} ms"


def resolve_window(run: Run, window) -> tuple[float, float] | str:
    """(t0, t1) in s, or why the window does not exist in this run (its event did not happen)."""
    if window is None:
        return (0.0, math.inf)
    event, a, b = window
    t = run.event(event)
    if t is None:
        return f"no {event} in this run"
    return (t + a, math.inf if b is None else t + b)


def _by_margin(base: dict, t: np.ndarray, v: np.ndarray, margin: np.ndarray, hold_s: np.ndarray) -> Result:
    """The result of a sample-wise check from each sample's margin (< 0: a violation; NaN counts as one):
    passed when none is negative, the first and the worst violation, and the time in violation (each
    sample held ``hold_s`` until the next)."""
    margin = np.where(np.isnan(margin), -np.inf, margin)
    bad = margin < 0
    worst = int(np.argmin(margin))
    first = int(np.argmax(bad)) if bad.any() else None
    return Result(**base, passed=not bad.any(), samples=len(t), margin=float(margin[worst]),
                  first=None if first is None else (float(t[first]), float(v[first])),
                  worst=(float(t[worst]), float(v[worst])) if bad.any() else None,
                  violation_s=float(hold_s[bad].sum()))


def _masked(run: Run, series, valid: str | None) -> np.ndarray:
    if valid is None:
        return np.ones(len(series.t_s), dtype=bool)
    v = run.signal(valid)
    if v.name.split(".")[0] == series.name.split(".")[0] and len(v.t_s) == len(series.t_s):
        held = v.values                     # the same frame: sample by sample
    else:
        held = v.at(series.t_s)
    return np.nan_to_num(held, nan=0.0) != 0


def _hold(t: np.ndarray) -> np.ndarray:
    """Each sample's hold time: to the next sample; the last one the median step."""
    if len(t) == 0:
        return t
    d = np.diff(t)
    last = float(np.median(d)) if len(d) else 0.0
    return np.append(d, last)


# -- in_range ----------------------------------------------------------------------------------------------
class InRange(Check):
    kind = "in_range"

    def __init__(self, signal, lo=None, hi=None, during=None, valid=None, name=None, req=None):
        super().__init__(name, req)
        if lo is None and hi is None:
            raise ConfigError(f"in_range {signal}: give lo, hi or both")
        if lo is not None and hi is not None and lo > hi:
            raise ConfigError(f"in_range {signal}: lo {lo:g} is above hi {hi:g}")
        self.signal, self.lo, self.hi, self.valid = signal, lo, hi, valid
        self.window = parse_window(during)

    def default_name(self) -> str:
        return self.signal

    def fields(self) -> dict:
        return {"signal": self.signal, "lo": self.lo, "hi": self.hi, "during": window_field(self.window),
                "valid": self.valid}

    def judge(self, run: Run) -> Result:
        s = run.signal(self.signal)
        base = dict(name=self.name, kind=self.kind, signal=self.signal, unit=s.unit, req=self.req,
                    window=window_text(self.window) + (f" where {self.valid}" if self.valid else ""),
                    limit=_bounds(self.lo, self.hi), lo=self.lo, hi=self.hi)
        span = resolve_window(run, self.window)
        if isinstance(span, str):
            return Result(**base, passed=False, reason=span)
        t0, t1 = span
        base["window_s"] = None if self.window is None else (t0, t1)
        keep = (s.t_s >= t0) & (s.t_s <= t1) & _masked(run, s, self.valid)
        base["plot"] = {"t": s.t_s, "v": s.values, "keep": keep}
        t, v = s.t_s[keep], s.values[keep]
        if len(t) == 0:
            return Result(**base, passed=False, reason=f"no samples of {self.signal} to judge")
        lo = -np.inf if self.lo is None else self.lo
        hi = np.inf if self.hi is None else self.hi
        with np.errstate(invalid="ignore"):
            margin = np.minimum(v - lo, hi - v)
        return _by_margin(base, t, v, margin, _hold(s.t_s)[keep])


def in_range(signal: str, lo: float | None = None, hi: float | None = None, during=None, *, valid: str | None = None,
             name: str | None = None, req: str | None = None) -> InRange:
    """``signal`` stays within [lo, hi] (either bound may be left out) in the window ``during``, counting
    only the samples where ``valid`` is non-zero."""
    return InRange(signal, lo, hi, during, valid, name, req)


# -- torque_sign -----------------------------------------------------------------------------------------
class TorqueSign(Check):
    kind = "torque_sign"

    def __init__(self, torque, demand, during=None, tolerance=0.0, name=None, req=None):
        super().__init__(name, req)
        if tolerance is None or not tolerance >= 0:
            raise ConfigError(f"torque_sign {torque}: tolerance must be >= 0")
        self.signal, self.demand, self.tolerance = torque, demand, float(tolerance)
        self.window = parse_window(during)

    def default_name(self) -> str:
        return f"{self.signal} has {self.demand}'s sign"

    def judge(self, run: Run) -> Result:
        s = run.signal(self.signal)
        base = dict(name=self.name, kind=self.kind, signal=self.signal, unit=s.unit, req=self.req,
                    window=window_text(self.window), limit=f"sign of {self.demand} (tolerance {self.tolerance:g})",
                    verb="against")
        span = resolve_window(run, self.window)
        if isinstance(span, str):
            return Result(**base, passed=False, reason=span)
        t0, t1 = span
        keep = (s.t_s >= t0) & (s.t_s <= t1)
        t, v = s.t_s[keep], s.values[keep]
        if len(t) == 0:
            return Result(**base, passed=False, reason=f"no samples of {self.signal} to judge")
        d = run.signal(self.demand).at(t)
        with np.errstate(invalid="ignore"):
            margin = np.sign(d) * v + self.tolerance        # < 0: the torque opposes the demand
        return _by_margin(base, t, v, margin, _hold(s.t_s)[keep])


def torque_sign(torque: str, demand: str, during=None, *, tolerance: float = 0.0, name: str | None = None,
                req: str | None = None) -> TorqueSign:
    """A TCU's ``torque`` never opposes the driver's ``demand``: sign(demand) x torque >= -``tolerance`` at each
    sample of ``torque`` (the demand held at its times) in the window ``during``."""
    return TorqueSign(torque, demand, during, tolerance, name, req)


# -- limit -------------------------------------------------------------------------------------------------
class Limit(Check):
    kind = "limit"

    def __init__(self, key, lo=None, hi=None, name=None, req=None):
        super().__init__(name, req)
        if lo is None and hi is None:
            raise ConfigError(f"limit {key}: give lo, hi or both")
        self.key, self.lo, self.hi = key, lo, hi

    def default_name(self) -> str:
        return self.key

    def fields(self) -> dict:
        return {"key": self.key, "lo": self.lo, "hi": self.hi}

    def judge(self, run: Run) -> Result:
        base = dict(name=self.name, kind=self.kind, signal=self.key, unit=_summary_unit(self.key), req=self.req,
                    window="in the run's summary", limit=_bounds(self.lo, self.hi), lo=self.lo,
                    hi=self.hi)
        value, found = _lookup(run.summary, self.key)
        if not found:
            import difflib
            close = difflib.get_close_matches(self.key, list(run.summary), n=3)
            fault = run.fault()
            why = (f"not in the summary of a run that did not finish ({fault})" if fault else
                   "not in the run's summary" + (f" (did you mean {', '.join(close)}?)" if close else ""))
            return Result(**base, passed=False, reason=why)
        if value is None:
            return Result(**base, passed=False, reason="no value (null in the summary: the run did not produce it)")
        if isinstance(value, bool):
            value = float(value)
        if not isinstance(value, (int, float)):
            raise ConfigError(f"limit {self.key}: the summary's value is not a number ({value!r})")
        v = float(value)
        base["plot"] = {"value": v}
        lo = -math.inf if self.lo is None else self.lo
        hi = math.inf if self.hi is None else self.hi
        margin = min(v - lo, hi - v) if not math.isnan(v) else -math.inf
        passed = margin >= 0
        return Result(**base, passed=passed, samples=1, margin=margin,
                      first=None if passed else (None, v), worst=None if passed else (None, v))


def _lookup(summary: dict, key: str) -> tuple:
    """(value, found) of ``key`` in the summary: ``a.b`` reaches into table ``a``; a key of a table may hold
    dots itself (``out_of_range_signals.TcuCmd.MuEstimate``): the longest one that matches is taken."""
    parts, value, i = key.split("."), summary, 0
    while i < len(parts):
        if not isinstance(value, dict):
            return None, False
        for j in range(len(parts), i, -1):
            k = ".".join(parts[i:j])
            if k in value:
                value, i = value[k], j
                break
        else:
            return None, False
    return value, True


def _summary_unit(key: str) -> str:
    leaf = key.rsplit(".", 1)[-1]
    for suffix, unit in (("_ms", "ms"), ("_us", "us"), ("_percent", "%"), ("_kmh", "km/h"), ("_s", "s")):
        if leaf.endswith(suffix):
            return unit
    return ""


def limit(summary_key: str, lo: float | None = None, hi: float | None = None, *, name: str | None = None,
          req: str | None = None) -> Limit:
    """The run summary's value ``summary_key`` (any key of ``hil run --json``; ``a.b`` reaches into a
    table) lies in [lo, hi]; a missing or null value fails."""
    return Limit(summary_key, lo, hi, name, req)


# -- responds ----------------------------------------------------------------------------------------------
def parse_condition(text: str) -> tuple[str, str, float]:
    """``"TcuStatus.Stage >= 1"`` -> (signal, op, value)."""
    m = _CONDITION.match(text or "")
    if not m:
        raise ConfigError(f"condition {text!r}: expected SIGNAL OP NUMBER, OP one of {' '.join(_OPS)} "
                          "(e.g. 'TcuStatus.Stage >= 1')")
    return m.group(1), m.group(2), float(m.group(3))


def _truth(run: Run, condition) -> tuple[np.ndarray, np.ndarray, object]:
    signal, op, value = condition
    s = run.signal(signal)
    with np.errstate(invalid="ignore"):
        return s.t_s, _OPS[op](s.values, value), s


class Responds(Check):
    kind = "responds"

    def __init__(self, trigger, condition, within_s, during=None, name=None, req=None):
        super().__init__(name, req)
        if within_s is None or within_s < 0:
            raise ConfigError(f"responds {condition}: within_s must be >= 0")
        self.trigger_text, self.condition_text, self.within_s = trigger, condition, float(within_s)
        self.trigger = parse_condition(trigger) if _CONDITION.match(trigger or "") else None
        self.condition = parse_condition(condition)
        self.window = parse_window(during)

    def default_name(self) -> str:
        return self.condition_text

    def fields(self) -> dict:
        return {"trigger": self.trigger_text, "condition": self.condition_text, "within_s": self.within_s,
                "during": window_field(self.window)}

    def judge(self, run: Run) -> Result:
        base = dict(name=self.name, kind=self.kind, signal=self.condition[0], unit="ms", req=self.req,
                    window=f"after each {self.trigger_text}" + ("" if self.window is None else
                                                                 f" {window_text(self.window)}"),
                    limit=f"{self.within_s * 1e3:g} ms", verb="later than",
                    note="" if run.mode == "realtime" else "lockstep: counted in exchange steps")
        span = resolve_window(run, self.window)
        if isinstance(span, str):
            return Result(**base, passed=False, reason=span)
        t0, t1 = span
        if self.trigger is None:
            t = run.event(self.trigger_text)
            triggers = np.array([] if t is None else [t])
            if t is None:
                return Result(**base, passed=False, reason=f"no {self.trigger_text} in this run")
        else:
            tt, truth, _ = _truth(run, self.trigger)
            rising = truth & ~np.concatenate([[False], truth[:-1]])
            triggers = tt[rising]
        triggers = triggers[(triggers >= t0) & (triggers <= t1)]
        ct, ctruth, cs = _truth(run, self.condition)
        # the figure draws the condition's signal in its own unit, its threshold, and after each trigger the
        # span it had to hold within (the result's values are reaction times in ms: not on this axis)
        base["plot"] = {"t": cs.t_s, "v": cs.values, "triggers": triggers, "unit": cs.unit,
                        "threshold": (self.condition[1], self.condition[2]), "within_s": self.within_s,
                        "ylabel": self.condition[0], "marks": False}
        if len(triggers) == 0:
            return Result(**base, passed=False, reason=f"no {self.trigger_text} to respond to")
        true_t = np.append(ct[ctruth], np.inf)          # never: an infinite reaction
        reaction = true_t[np.searchsorted(true_t, triggers, side="left")] - triggers
        bad = reaction > self.within_s + 1e-12
        worst = int(np.argmax(reaction))
        first = int(np.argmax(bad)) if bad.any() else None
        return Result(**base, passed=not bad.any(), samples=len(triggers),
                      margin=float(self.within_s - reaction[worst]) * 1e3,
                      first=None if first is None else (float(triggers[first]), float(reaction[first] * 1e3)),
                      worst=(float(triggers[worst]), float(reaction[worst] * 1e3)) if bad.any() else None,
                      violation_s=float(np.sum(np.minimum(reaction[bad], run.duration_s or np.inf) - self.within_s)))


def responds(trigger: str, condition: str, within_s: float, during=None, *, name: str | None = None,
             req: str | None = None) -> Responds:
    """After each ``trigger`` (an event name, e.g. ``"fault"``, or the rising edge of a condition such as
    ``"PlantSensor.MotorSpeed > 70"``), ``condition`` (``"SIGNAL OP NUMBER"``) holds within ``within_s``.
    The figures are the reaction times in ms."""
    return Responds(trigger, condition, within_s, during, name, req)


# -- cycle_time --------------------------------------------------------------------------------------------
class CycleTime(Check):
    kind = "cycle_time"

    def __init__(self, frame, nominal_s, tolerance_s, during=None, name=None, req=None, max_outside_fraction=0.0):
        super().__init__(name, req)
        if not nominal_s or nominal_s <= 0 or tolerance_s is None or tolerance_s < 0:
            raise ConfigError(f"cycle_time {frame}: nominal_s must be > 0 and tolerance_s >= 0")
        if max_outside_fraction is None or not 0.0 <= max_outside_fraction < 1.0:
            raise ConfigError(f"cycle_time {frame}: max_outside_fraction must be in [0, 1), got {max_outside_fraction!r}")
        self.frame, self.nominal_s, self.tolerance_s = frame, float(nominal_s), float(tolerance_s)
        self.max_outside_fraction = float(max_outside_fraction)
        self.window = parse_window(during)

    def default_name(self) -> str:
        return f"{self.frame} cycle time"

    def fields(self) -> dict:
        return {"frame": self.frame, "nominal_s": self.nominal_s, "tolerance_s": self.tolerance_s,
                "during": window_field(self.window), "max_outside_fraction": self.max_outside_fraction or None}

    def judge(self, run: Run) -> Result:
        realtime = run.mode == "realtime"
        base = dict(name=self.name, kind=self.kind, signal=self.frame, unit="ms", req=self.req,
                    window=window_text(self.window), lo=(self.nominal_s - self.tolerance_s) * 1e3,
                    hi=(self.nominal_s + self.tolerance_s) * 1e3,
                    limit=f"{self.nominal_s * 1e3:g} ± {self.tolerance_s * 1e3:g} ms", verb="cycle outside",
                    note="receive wall time" if realtime else
                    f"lockstep: counted in exchange steps of {run.period_s * 1e3:g} ms, not wall time")
        span = resolve_window(run, self.window)
        if isinstance(span, str):
            return Result(**base, passed=False, reason=span)
        t0, t1 = span
        t, wall = run.frame_times(self.frame)
        keep = (t >= t0) & (t <= t1)
        t, clock = t[keep], (wall if realtime else t)[keep]
        if len(t) < 2:
            return Result(**base, passed=False, reason=f"{len(t)} {self.frame} frame(s): no cycle to measure")
        order = np.argsort(clock, kind="stable")
        t, clock = t[order], clock[order]
        dt = np.diff(clock)
        # a frame that stops before the run does is one more interval, from its last frame to the run's end
        # within the window: in real time the bus's record (the plant's frames go on until it gives up on a
        # frozen TCU), in lockstep the steps the run was to make (the plant waits at the frozen TCU's step)
        end = run.frames_end()[1] if realtime else run.planned_duration_s
        if not math.isinf(t1):
            end = min(end, clock[-1] + (t1 - t[-1]))
        silent = 0                          # the cycles a frame that stopped early left out, beyond the one
        if end - clock[-1] > self.nominal_s + self.tolerance_s + run.period_s + 1e-9:
            silent = max(int((end - clock[-1]) / self.nominal_s) - 1, 0)
            dt = np.append(dt, end - clock[-1])
            t = np.append(t, t[-1] + (end - clock[-1]))
            base["note"] += f"; no {self.frame} in the last {(end - clock[-1]) * 1e3:.0f} ms of the run"
        err = np.abs(dt - self.nominal_s)
        margin = self.tolerance_s - err
        bad = margin < -1e-9
        # the intervals that may lie outside: the worst floor(fraction * n); the margin is that of the worst
        # interval beyond them (with no allowance, of the worst interval)
        # a silence counts as the cycles it left out: each of them an interval outside
        n_out, n = int(bad.sum()) + silent, len(dt) + silent
        allowed = math.floor(self.max_outside_fraction * n + 1e-9)
        kept_margin = float(np.sort(margin)[min(max(allowed - silent, 0), len(dt) - 1)])
        if self.max_outside_fraction:
            base["note"] += (f"; {n_out} of {n} intervals outside, at most {allowed} "
                             f"({self.max_outside_fraction * 100:g} %) allowed")
        worst = int(np.argmin(margin))
        first = int(np.argmax(bad)) if bad.any() else None
        base["plot"] = {"t": t[1:], "v": dt * 1e3, "ylabel": f"{self.frame} interval"}
        base["window_s"] = None if self.window is None else (t0, t1)
        return Result(**base, passed=n_out <= allowed, samples=n, margin=kept_margin * 1e3,
                      first=None if first is None else (float(t[first + 1]), float(dt[first] * 1e3)),
                      worst=(float(t[worst + 1]), float(dt[worst] * 1e3)) if bad.any() else None,
                      violation_s=float(dt[bad].sum()))


def cycle_time(frame: str, nominal_s: float, tolerance_s: float, during=None, *, name: str | None = None,
               req: str | None = None, max_outside_fraction: float = 0.0) -> CycleTime:
    """Frame ``frame`` (its DBC name) arrives every ``nominal_s`` ± ``tolerance_s``: in receive wall time in
    a real-time run, in exchange steps in lockstep.  ``max_outside_fraction``: the share of intervals that
    may lie outside (default none).  Why a share: in real time a period whose deadline was missed (a run
    allows ``[bus] max_missed_fraction`` of them) puts two intervals of a TCU that answers each reading
    outside any tolerance below a period, the gap and the catch-up; in lockstep such a TCU's interval is
    always one step, so the share costs nothing there."""
    return CycleTime(frame, nominal_s, tolerance_s, during, name, req, max_outside_fraction)


# -- settles -----------------------------------------------------------------------------------------------
class Settles(Check):
    kind = "settles"

    def __init__(self, signal, band, within_s, hold_s, after=None, valid=None, name=None, req=None):
        super().__init__(name, req)
        try:
            lo, hi = (None if b is None else float(b) for b in band)
        except (TypeError, ValueError):
            raise ConfigError(f"settles {signal}: band must be (lo, hi), not {band!r}") from None
        if within_s is None or within_s < 0 or hold_s is None or hold_s < 0:
            raise ConfigError(f"settles {signal}: within_s and hold_s must be >= 0")
        self.signal, self.lo, self.hi, self.valid = signal, lo, hi, valid
        self.within_s, self.hold_s = float(within_s), float(hold_s)
        self.window = parse_window(after)

    def default_name(self) -> str:
        return f"{self.signal} settles"

    def fields(self) -> dict:
        after = None if self.window is None else (self.window[0] if not self.window[1] else
                                                  [self.window[0], self.window[1]])
        band = [-math.inf if self.lo is None else self.lo, math.inf if self.hi is None else self.hi]
        return {"signal": self.signal, "band": band, "within_s": self.within_s,
                "hold_s": self.hold_s, "after": after, "valid": self.valid}

    def judge(self, run: Run) -> Result:
        s = run.signal(self.signal)
        after = "the start" if self.window is None else f"{self.window[0]}" + (
            f"{self.window[1] * 1e3:+.0f} ms" if self.window[1] else "")
        base = dict(name=self.name, kind=self.kind, signal=self.signal, unit=s.unit, req=self.req, lo=self.lo,
                    hi=self.hi, window=f"within {self.within_s * 1e3:g} ms of {after} "
                    f"(held {self.hold_s * 1e3:g} ms)" + (f" where {self.valid}" if self.valid else ""),
                    limit=_bounds(self.lo, self.hi), verb="not settled in", margin_unit="ms")
        span = resolve_window(run, self.window)
        if isinstance(span, str):
            return Result(**base, passed=False, reason=span)
        t0 = span[0]
        base["window_s"] = (t0, t0 + self.within_s + self.hold_s)
        keep = (s.t_s >= t0) & _masked(run, s, self.valid)
        base["plot"] = {"t": s.t_s, "v": s.values, "keep": keep}
        t, v, hold = s.t_s[keep], s.values[keep], _hold(s.t_s)[keep]
        if len(t) == 0:
            return Result(**base, passed=False, reason=f"no samples of {self.signal} to judge")
        lo = -np.inf if self.lo is None else self.lo
        hi = np.inf if self.hi is None else self.hi
        with np.errstate(invalid="ignore"):
            dist = np.maximum(lo - v, v - hi)             # > 0: outside the band by this much
        dist = np.where(np.isnan(dist), np.inf, dist)
        out = dist > 0
        end = t[-1] + hold[-1]
        # for each sample, the time of the next sample out of the band (the log's end when none)
        idx = np.where(out)[0]
        nxt = np.searchsorted(idx, np.arange(len(t)), side="left")
        next_out = np.where(nxt < len(idx), t[idx[np.minimum(nxt, len(idx) - 1)]] if len(idx) else end, end)
        holds = ~out & (next_out - t >= self.hold_s - 1e-9)
        settled_at = float(t[np.argmax(holds)]) if holds.any() else None
        settle = None if settled_at is None else settled_at - t0
        passed = settle is not None and settle <= self.within_s + 1e-9
        late = out & (t > t0 + self.within_s)
        first = int(np.argmax(late)) if late.any() else None
        worst = int(np.argmax(np.where(late, dist, -np.inf))) if late.any() else None
        reason = "" if passed or first is not None else (
            f"not settled: in the band only from {settled_at:.3f} s" if settle is not None else
            f"the log ends {end - t0:.3f} s after {after}: too short to see {self.hold_s * 1e3:g} ms held")
        return Result(**base, passed=passed, samples=len(t), reason=reason,
                      margin=None if settle is None else (self.within_s - settle) * 1e3,
                      first=None if passed or first is None else (float(t[first]), float(v[first])),
                      worst=None if passed or worst is None else (float(t[worst]), float(v[worst])),
                      violation_s=0.0 if passed else float(hold[late].sum()))


def settles(signal: str, band, within_s: float, hold_s: float, after=None, *, valid: str | None = None,
            name: str | None = None, req: str | None = None) -> Settles:
    """``signal`` enters ``band`` = (lo, hi) within ``within_s`` of ``after`` (an event, or (event, offset
    s); the run's start by default) and then stays in it for ``hold_s``.  Its margin is the time to spare
    in ms."""
    return Settles(signal, band, within_s, hold_s, after, valid, name, req)
