"""The rail along a run and the driver's demand: what changes with time outside the wheelset.

``RailSchedule``: the rail as segments in time (dry -> wet -> contaminated patch -> dry), each with its
friction curve (plant/friction.py) and a transition length.  Segment i starts at ``start_s``; over its
``transition_s`` the rail blends linearly from what it was into the segment's curve::

    alpha_i(t) = clip((t - start_i) / transition_i, 0, 1)         (a step at start_i when transition_i = 0)
    mu_0(v_s, v_t, t) = curve_0(v_s, v_t)
    mu_i(v_s, v_t, t) = (1 - alpha_i(t)) mu_(i-1)(v_s, v_t, t) + alpha_i(t) curve_i(v_s, v_t)
    mu(v_s, v_t, t)   = mu_n(v_s, v_t, t)

The same expression runs on CasADi symbols (the plant) and on numpy arrays (the truth the metrics
use), so the two cannot drift.  ``peak(t, v_t)`` is the true current curve's peak (creep speed km/h,
mu): what the closed-loop metrics judge a controller against and what no TCU ever sees.

Degraded adhesion (``recovery``, optional): a contaminated contact is cleaned by the energy the
wheel dissipates in it (Meli, Ridolfi and Rindi, Meccanica 49 (2014) 919-937; Allotta et al.,
Tribol. Int.): the rail's curve recovers towards the segment's dry reference as the specific energy
``E`` dissipated in the contact grows::

    dE/dt       = F_x w / A_contact ... lumped here as  P(t) = mu N w  (W, w = v_s / 3.6 the slip velocity)
    rho(E)      = 1 - exp(-E / E_clean)                 cleaned fraction, E in J
    mu_rec      = mu + rho (mu_ref - mu)                mu_ref: the ``recovers_to`` segment's curve

``E`` is integrated by the plant per exchange period (the recovery is slow against the period) and
enters the CasADi step as a parameter; a segment without ``recovers_to`` does not recover.

``DemandProfile``: the driver's demand as points (t_s, demand in *equivalent mu*: the traction force
asked of this wheelset divided by its normal force), linear between points, held after the last;
a step is two points at the same time.  The motor torque asked is ``mu_d * torque_per_mu_nm``.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

from .friction import PEAK_SEARCH_KMH, FrictionCurve, PolachCurve

#: creep-speed grid (km/h) the truth's peak is searched on, refined by a parabola through the best three
_PEAK_GRID_KMH = np.linspace(PEAK_SEARCH_KMH[0], PEAK_SEARCH_KMH[1] / 2, 1501)
#: the truth's peak is cached per train speed rounded to this (m/s) outside transitions; Polach peaks move
#: by well under 0.1 % over it
_SPEED_QUANTUM_MS = 0.05
#: curves' mu on the peak search's grid kept (``RailSchedule._curve_mu``): 12 kB each
_GRID_CACHE_ENTRIES = 64
#: past a transition's end by this much, its alpha is 1 to the bit whatever the rounding of (t - start) / length
_STEADY_MARGIN_S = 1e-9


@dataclass(frozen=True)
class RailSegment:
    start_s: float
    curve: FrictionCurve | PolachCurve
    transition_s: float = 0.0
    label: str = ""


@dataclass(frozen=True)
class Recovery:
    """Degraded adhesion that recovers with the dissipated energy (module docstring)."""
    energy_clean_j: float          # E_clean: energy for 63 % recovery
    reference: FrictionCurve | PolachCurve


@dataclass
class RailSchedule:
    """Segments in time order (the first starts at 0); module docstring."""

    segments: tuple[RailSegment, ...]
    recovery: dict[int, Recovery] = field(default_factory=dict)     # segment index -> its recovery
    _cache: dict = field(default_factory=dict, repr=False, compare=False)
    _grid_cache: dict = field(default_factory=dict, repr=False, compare=False)
    #: (from, until, alphas, index): a span of time without a transition under way, where both are constant
    _steady: tuple = field(default=(math.inf, -math.inf, (), 0), repr=False, compare=False)

    def __post_init__(self):
        if not self.segments or self.segments[0].start_s != 0.0:
            raise ValueError("the first rail segment must start at 0 s")
        for a, b in zip(self.segments, self.segments[1:]):
            if b.start_s < a.start_s + a.transition_s:
                raise ValueError(f"rail segment at {b.start_s:g} s starts before the previous one's transition ends")

    def weights(self, t_s: float) -> tuple[float, ...]:
        """alpha_i(t) for segments 1..n (module docstring)."""
        steady = self._steady
        if steady[0] <= t_s < steady[1]:
            return steady[2]
        out = []
        for s in self.segments[1:]:
            if s.transition_s <= 0.0:
                out.append(1.0 if t_s >= s.start_s else 0.0)
            else:
                out.append(min(max((t_s - s.start_s) / s.transition_s, 0.0), 1.0))
        out = tuple(out)
        self._remember_steady(t_s, out)
        return out

    def _remember_steady(self, t_s: float, alphas: tuple[float, ...]) -> None:
        """When ``t_s`` lies between the end of segment k's transition (plus ``_STEADY_MARGIN_S``, so every
        alpha has reached exactly 1 or 0) and segment k + 1's start, every time there has these alphas and
        index k: kept for the next call (the truth asks every period)."""
        k = self.index_at(t_s)
        seg = self.segments[k]
        start = seg.start_s + seg.transition_s + _STEADY_MARGIN_S if k else -math.inf
        until = self.segments[k + 1].start_s if k + 1 < len(self.segments) else math.inf
        if start <= t_s < until:
            self._steady = (start, until, alphas, k)

    def window_at(self, t0_s: float, t1_s: float, margin_s: float = 1e-6) -> tuple[int, int]:
        """The segments (lo, hi) whose blend is the rail over [t0_s, t1_s] (``mu_casadi``'s ``window``):
        lo has ended its transition by t0_s and hi + 1 begins after t1_s, each with ``margin_s`` to spare (a
        wider window is the same number, a narrower one would not be)."""
        lo = self.index_at(t0_s - margin_s)
        s = self.segments[lo]
        if lo and t0_s - margin_s < s.start_s + s.transition_s:
            lo -= 1
        return lo, self.index_at(t1_s + margin_s)

    def index_at(self, t_s: float) -> int:
        """The segment whose start is the last at or before ``t_s``."""
        steady = self._steady
        if steady[0] <= t_s < steady[1]:
            return steady[3]
        i = 0
        for j, s in enumerate(self.segments):
            if t_s >= s.start_s:
                i = j
        return i

    def _blend(self, curves_mu, alphas):
        mu = curves_mu[0]
        for a, m in zip(alphas, curves_mu[1:]):
            mu = (1 - a) * mu + a * m
        return mu

    def mu_casadi(self, creep_speed_kmh, train_speed_ms, t, cleaned=None, window=None):
        """mu(v_s, v_t, t) on CasADi expressions; ``cleaned``: rho per recovering segment (symbols).

        ``window`` = (lo, hi): the blend of segments lo..hi only, curve_lo as its base.  Where segment lo
        has ended its transition (alpha_lo = 1) and segment hi + 1 has not begun (alpha = 0), it is the
        same number as the whole blend, to the bit: (1 - 1) mu + 1 c = c and (1 - 0) mu + 0 c = mu
        (``window_at`` gives the window of a time span)."""
        import casadi as ca

        lo, hi = window if window is not None else (0, len(self.segments) - 1)
        mus = []
        for i in range(lo, hi + 1):
            mu = self.segments[i].curve.mu_casadi(creep_speed_kmh, train_speed_ms)
            if i in self.recovery and cleaned is not None:
                ref = self.recovery[i].reference.mu_casadi(creep_speed_kmh, train_speed_ms)
                mu = mu + cleaned[list(self.recovery).index(i)] * (ref - mu)
            mus.append(mu)
        alphas = []
        for s in self.segments[lo + 1:hi + 1]:
            if s.transition_s <= 0.0:
                alphas.append(ca.if_else(t >= s.start_s, 1.0, 0.0))
            else:
                alphas.append(ca.fmin(ca.fmax((t - s.start_s) / s.transition_s, 0.0), 1.0))
        return self._blend(mus, alphas)

    def mu_at(self, creep_speed_kmh, train_speed_ms: float, t_s: float, cleaned=()):
        """mu on numpy arrays of creep speed, at one train speed and time.  Only the segments that weigh
        at ``t_s`` are evaluated: from the last whose alpha is 1 to the last whose alpha is above 0 (the
        same numbers as the whole blend, ``mu_casadi``)."""
        alphas = self.weights(t_s)
        lo = max((j for j, a in enumerate(alphas, start=1) if a == 1.0), default=0)
        hi = max((j for j, a in enumerate(alphas, start=1) if a > 0.0), default=0)
        mus = []
        for i in range(lo, max(hi, lo) + 1):
            mu = self._curve_mu(self.segments[i].curve, creep_speed_kmh, train_speed_ms)
            if i in self.recovery and cleaned:
                rho = cleaned[list(self.recovery).index(i)]
                mu = mu + rho * (self._curve_mu(self.recovery[i].reference, creep_speed_kmh, train_speed_ms) - mu)
            mus.append(mu)
        return self._blend(mus, alphas[lo:max(hi, lo)])

    def _curve_mu(self, curve, creep_speed_kmh, train_speed_ms: float):
        """``curve.mu_at``; on the peak search's grid kept per (curve, train speed), read-only: over a
        transition or a recovery only the weights change, not the curves, and the truth asks every period
        (the same arrays, so the same blend to the bit)."""
        if creep_speed_kmh is not _PEAK_GRID_KMH:
            return curve.mu_at(creep_speed_kmh, train_speed_ms)
        key = (id(curve), train_speed_ms)
        hit = self._grid_cache.get(key)
        if hit is None:
            if len(self._grid_cache) >= _GRID_CACHE_ENTRIES:
                self._grid_cache.clear()
            hit = np.asarray(curve.mu_at(creep_speed_kmh, train_speed_ms))
            hit.setflags(write=False)
            self._grid_cache[key] = hit
        return hit

    def peak(self, t_s: float, train_speed_ms: float, cleaned=()) -> tuple[float, float]:
        """(creep speed km/h, mu) at the peak of the true curve at ``t_s`` and ``train_speed_ms``."""
        alphas = self.weights(t_s)
        key = (alphas, round(train_speed_ms / _SPEED_QUANTUM_MS), tuple(round(c, 3) for c in cleaned))
        hit = self._cache.get(key)
        if hit is None:
            v_t = round(train_speed_ms / _SPEED_QUANTUM_MS) * _SPEED_QUANTUM_MS
            mu = self.mu_at(_PEAK_GRID_KMH, v_t, t_s, cleaned)
            i = int(np.clip(np.argmax(mu), 1, len(mu) - 2))
            y0, y1, y2 = mu[i - 1], mu[i], mu[i + 1]
            den = y0 - 2 * y1 + y2
            shift = 0.5 * (y0 - y2) / den if den < 0 else 0.0
            h = _PEAK_GRID_KMH[1] - _PEAK_GRID_KMH[0]
            v = float(_PEAK_GRID_KMH[i] + shift * h)
            hit = (v, float(self.mu_at(np.array([v]), v_t, t_s, cleaned)[0]))
            if len(self._cache) > 100_000:
                self._cache.clear()
            self._cache[key] = hit
        return hit

    @property
    def transitions_s(self) -> tuple[float, ...]:
        """The start of every segment after the first (where the rail changes)."""
        return tuple(s.start_s for s in self.segments[1:])


@dataclass(frozen=True)
class DemandProfile:
    """The driver's demand (equivalent mu) as points (t_s, mu_d), linear between them (module docstring)."""

    times_s: tuple[float, ...]
    demand_mu: tuple[float, ...]

    def __post_init__(self):
        if not self.times_s or len(self.times_s) != len(self.demand_mu):
            raise ValueError("a demand profile needs points (t_s, mu), as many times as values")
        if self.times_s[0] != 0.0:
            raise ValueError("a demand profile starts at t = 0")
        if any(b < a for a, b in zip(self.times_s, self.times_s[1:])):
            raise ValueError("a demand profile's times must not decrease")

    def at(self, t_s: float) -> float:
        """mu_d(t): linear between points; at a step (two points at one time) the later value."""
        ts, ys = self.times_s, self.demand_mu
        if t_s >= ts[-1]:
            return ys[-1]
        j = bisect.bisect_right(ts, t_s)                     # ts[j-1] <= t < ts[j] (numpy's searchsorted, right)
        t0, t1 = ts[j - 1], ts[j]
        return ys[j - 1] + (ys[j] - ys[j - 1]) * (t_s - t0) / (t1 - t0)

    def casadi(self, t):
        """The same on a CasADi expression (piecewise linear in t)."""
        import casadi as ca

        out = self.demand_mu[0]
        for (t0, y0), (t1, y1) in zip(zip(self.times_s, self.demand_mu), zip(self.times_s[1:], self.demand_mu[1:])):
            if t1 == t0:
                out = ca.if_else(t >= t1, y1, out)
            else:
                out = ca.if_else(t >= t0, y0 + (y1 - y0) * ca.fmin((t - t0) / (t1 - t0), 1.0), out)
        return out
