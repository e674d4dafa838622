"""The control laws (identifier/control/__init__.py lists them; base.py holds the interface).

``demand``            open loop: the driver's demand (the paper's runs; excitation added by the identifier).
``readhesion``        the industrial re-adhesion baseline: a slip is flagged when the creep exceeds a threshold
                      or rises faster than a rate; the torque is cut to a fraction of the observer's load
                      torque, held until the creep falls back, then ramped back towards the demand.
``constant_creep``    the usual industrial baseline (arXiv 2406.13650): the creep held at a fixed set-point
                      taken from the nominal (dry) curve's peak creep.
``extremum_seeking``  perturbation-based peak tracking: a sine dither on the creep set-point, the observer's
                      mu^ demodulated by it gives the slope d mu / d v_s, the set-point climbs it (Ariyur and
                      Krstic's scheme; J. Adv. Transp. 2019, 6270515 for its use on a locomotive).
``identified``        extremum seeking placed by what the TCU learns of the rail: at each change of rail mu^
                      shows (a drop or a recovery) the creep falls to a bound safe on every rail of the
                      prior family and climbs from there until mu^ stops rising; a confirmed curve whose
                      peak creep the creep has passed well beyond moves the set-point to it (kept inside the
                      90 % peak-creep interval); the dither corrects both and carries on alone otherwise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from .base import ControlInput, Controller, CreepLoop

_LOOP_DEFAULTS = {"bandwidth_rad_s": 150.0, "integral_rad_s": 20.0}
_LOOP_RANGES = {"bandwidth_rad_s": (1.0, 2000.0), "integral_rad_s": (0.0, 500.0)}


class Demand(Controller):
    """Open loop: T_cmd = T_demand."""
    name = "demand"

    def torque_nm(self, x: ControlInput) -> float:
        return x.demand_nm


class Readhesion(Controller):
    """Threshold re-adhesion (module docstring).  Slip when v_s > trigger * v_N or dv_s/dt > rate; then
    T = cut * T^_L, falling further by ``reduce_per_s`` x T_demand per second until v_s < release * v_N; then T
    rises by ``ramp_per_s`` x T_demand per second."""
    name = "readhesion"
    defaults = {"trigger_fraction": 1.2, "release_fraction": 0.8, "rate_kmh_per_s": 40.0, "cut_fraction": 0.7,
                "reduce_per_s": 2.0, "ramp_per_s": 0.5, "rate_filter_s": 0.005}
    ranges = {"trigger_fraction": (0.1, 20.0), "release_fraction": (0.05, 10.0), "rate_kmh_per_s": (0.1, 1e4),
              "cut_fraction": (0.0, 1.0), "reduce_per_s": (0.0, 100.0), "ramp_per_s": (0.01, 100.0),
              "rate_filter_s": (0.0, 1.0)}

    def __init__(self, vehicle, nominal_peak_creep_kmh, options=None):
        super().__init__(vehicle, nominal_peak_creep_kmh, options)
        if self.options["release_fraction"] >= self.options["trigger_fraction"]:
            raise ValueError("release_fraction must be below trigger_fraction")
        self.cut = False
        self.torque = None
        self._creep_prev = None
        self._rate = 0.0

    def torque_nm(self, x: ControlInput) -> float:
        o, v_n = self.options, self.nominal_peak_creep_kmh
        if self._creep_prev is not None:          # dv_s/dt, first-order filtered
            raw = (x.creep_speed_kmh - self._creep_prev) / x.period_s
            a = x.period_s / (o["rate_filter_s"] + x.period_s)
            self._rate += a * (raw - self._rate)
        self._creep_prev = x.creep_speed_kmh
        if self.torque is None:
            self.torque = x.demand_nm
        if not self.cut and (x.creep_speed_kmh > o["trigger_fraction"] * v_n or self._rate > o["rate_kmh_per_s"]):
            self.cut = True
            self.torque = min(self.torque, o["cut_fraction"] * max(x.load_torque_nm, 0.0))
        elif self.cut and x.creep_speed_kmh < o["release_fraction"] * v_n:
            self.cut = False
        if self.cut:
            self.torque -= o["reduce_per_s"] * x.demand_nm * x.period_s
        else:
            self.torque += o["ramp_per_s"] * x.demand_nm * x.period_s
        self.torque = min(max(self.torque, 0.0), x.demand_nm)
        return self.torque


class ConstantCreep(Controller):
    """v* = set_fraction * v_N, the nominal curve's peak creep; ``CreepLoop`` holds it."""
    name = "constant_creep"
    defaults = {"set_fraction": 1.0, **_LOOP_DEFAULTS}
    ranges = {"set_fraction": (0.05, 20.0), **_LOOP_RANGES}

    def __init__(self, vehicle, nominal_peak_creep_kmh, options=None):
        super().__init__(vehicle, nominal_peak_creep_kmh, options)
        self.loop = CreepLoop(vehicle, self.options["bandwidth_rad_s"], self.options["integral_rad_s"])

    def torque_nm(self, x: ControlInput) -> float:
        return self.loop.torque_nm(x, self.options["set_fraction"] * self.nominal_peak_creep_kmh)


class ExtremumSeeking(Controller):
    """Set-point v^ + a sin(2 pi f t); slope g = LPF(HPF(mu^) sin(2 pi f t)); dv^/dt = k g (while the creep loop,
    not the demand, limits the torque; v^ then stays no more than ``carry_kmh`` above the measured creep, by
    default twice the dither, so the dither's trough stays clear of the creep the demand carries).  The dither's phase is
    shifted by ``lag_s``, the observer's lag behind the true mu (2 / its pole).

    A change of rail moves mu^ by far more than the dither can (docs/design/control.md measures both):
    demodulated, that step is a slope of whatever sign the dither's phase gives, and it can throw v^ far
    past the new rail's peak within a tenth of a second.  So when |mu^ - mean| exceeds ``reset_mu`` the
    estimate starts again (mean = mu^, slope = 0) and v^ stays where it is (0: never)."""
    name = "extremum_seeking"
    defaults = {"dither_kmh": 0.08, "dither_hz": 8.0, "gain": 300.0, "filter_s": 0.1, "lag_s": 0.004,
                "min_kmh": 0.2, "max_kmh": 12.0, "reset_mu": 0.05, "carry_kmh": 0.16, **_LOOP_DEFAULTS}
    ranges = {"dither_kmh": (0.0, 2.0), "dither_hz": (0.1, 200.0), "gain": (0.0, 1e5), "filter_s": (0.001, 10.0),
              "lag_s": (0.0, 1.0), "min_kmh": (0.0, 30.0), "max_kmh": (0.1, 30.0), "reset_mu": (0.0, 1.0),
              "carry_kmh": (0.0, 30.0), **_LOOP_RANGES}

    def __init__(self, vehicle, nominal_peak_creep_kmh, options=None):
        super().__init__(vehicle, nominal_peak_creep_kmh, options)
        self.loop = CreepLoop(vehicle, self.options["bandwidth_rad_s"], self.options["integral_rad_s"])
        self.v_hat = nominal_peak_creep_kmh
        self._mu_mean = None
        self._slope = 0.0

    def torque_nm(self, x: ControlInput) -> float:
        o = self.options
        phase = 2 * math.pi * o["dither_hz"] * x.t_s
        a = x.period_s / (o["filter_s"] + x.period_s)
        if self._mu_mean is None:
            self._mu_mean = x.mu_hat
        if o["reset_mu"] and abs(x.mu_hat - self._mu_mean) > o["reset_mu"]:   # a change of rail: start again
            self._mu_mean, self._slope = x.mu_hat, 0.0
        self._mu_mean += a * (x.mu_hat - self._mu_mean)                 # high pass: mu^ minus its mean
        demod = (x.mu_hat - self._mu_mean) * math.sin(phase - 2 * math.pi * o["dither_hz"] * o["lag_s"])
        self._slope += a * (demod - self._slope)                          # low pass of the demodulated slope
        if self.loop.limited:
            self.v_hat += o["gain"] * self._slope * x.period_s
        else:                       # the demand limits: keep v^ just above the creep it carries
            self.v_hat = max(min(self.v_hat, x.creep_speed_kmh + o["carry_kmh"]), o["min_kmh"])
        self.v_hat = min(max(self.v_hat, o["min_kmh"]), o["max_kmh"])
        return self.loop.torque_nm(x, self.v_hat + o["dither_kmh"] * math.sin(phase))


@dataclass
class _Scan:
    """The climb of ``Identified`` (its class docstring) while it lasts."""
    time_s: float = 0.0                       # since it began
    mu: float | None = None                   # mu^, filtered over scan_filter_s
    best_mu: float = -math.inf                # the best filtered mu^ ...
    best_kmh: float = math.nan                # ... and the creep it was seen at
    rise: tuple[float, float] | None = None   # (mu, creep) at the last rise of scan_drop_mu


class Identified(ExtremumSeeking):
    """Extremum seeking placed by what the TCU learns of the rail (module docstring).

    **A change of rail** (mu^ leaves its mean, extremum seeking's first-order filter of ``filter_s``, by
    more than ``change_mu``, up or down, while the creep is held): the set-point drops to at most ``cap_kmh`` and,
    ``scan_settle_s`` later, climbs at ``scan_kmh_per_s`` while mu^ (filtered over ``scan_filter_s``) keeps
    rising; once it has fallen ``scan_drop_mu`` below the best seen, the set-point returns to the creep
    where the best was seen and extremum seeking takes over from there (its estimate restarted).  The
    scan also ends when the demand, not the creep loop, limits the torque (the rail carries the demand).
    Why: with the peak creep of the new rail unknown, the creep the old rail carried may be past twice
    it (macro-slip) on a wet patch after a dry rail, and on a dry rail after a patch whose peak lay far
    out; ``cap_kmh`` = 0.7 km/h is below twice the lowest peak creep of the TCU's prior family
    (``default``: 0.4 km/h) by the dither's amplitude and the creep loop's overshoot (about 0.05 km/h
    each): on a patch whose peak is the lowest, the climb from the cap ends near it and the dither rides
    on top.  A climb at 4 km/h/s finds a peak the dither would take seconds to reach.  During a scan the
    change test is off: the scan itself moves mu^.

    **Past a peak**: a change of rail can leave mu^ almost where it was (a dry rail after a patch whose
    peak lay far out: the dry curve's tail, at the creep the patch carried, gives about the patch's peak
    mu).  The dither then sees the fall: when its slope estimate 2 LPF(demod) / a stays below
    -``past_slope`` (per km/h) for ``past_s`` while the creep loop holds a creep above ``cap_kmh``, the
    set-point drops and climbs as at a change of rail, instead of the dither walking it down at
    ``gain`` x its slope (docs/design/control.md has the macro-slip that showed it).  Without a dither
    (``dither_kmh`` 0) there is no slope estimate and no such drop.

    **A better rail**: a rail that recovers over a transition can raise mu^ too slowly for the change test
    (mu^ stays near its own mean) and too little at the creep held (a dry rail whose peak lies far below
    that creep, after a patch whose peak lay far out).  While the creep loop holds a
    creep above ``cap_kmh`` outside a scan, mu^ filtered over ``scan_filter_s`` is compared with its lowest
    value since then: a rise of more than ``rise_mu`` drops the set-point and climbs as at a change of rail
    (0: off; docs/design/control.md has the macro-slip that showed it and the A/B).

    **A bound on the creep held**: ``max_kmh`` is 1.6 km/h here (extremum seeking's 12), twice the lowest peak
    creep of a dry rail in the TCU's prior (0.8 km/h: hil/benchmarks/control.py's dry rails).  Why: on a
    patch whose peak lies far out (up to 3 km/h in the ``default`` family) a return to dry rail within
    about 0.1 s puts the creep held past twice the dry peak creep before mu^ at that creep has moved by
    more than its noise, so no test above can act in time; below the bound the return cannot make a
    macro-slip.  It costs such patches the mu between the bound and their peak (docs/design/control.md
    measures both).

    **A confirmed curve** whose peak creep the creep has passed ``jump_ratio``-fold moves the set-point
    to ``hold_fraction`` x that peak creep (clipped to its 90 % interval); the dither corrects it.  Why
    the condition: in closed loop a drop's samples straddle the change of rail while the loop holds the
    creep, and a fall of mu that the rail made looks, to an identifier of one static curve, like the fall
    past a peak at the newest creeps; ``gp`` dates the change and drops the samples before it
    (identifier/strategies/gp.py), but a strategy that does not would claim a peak just below the creep
    reached, and an ``unconfirmed`` best estimate may be the working range's bound (docs/design/control.md
    measures both).  Only the peak *creep* is used: the peak mu of a curve fitted across two rails is
    the least reliable part of it.  Once the demand has passed through for ``rearm_s`` after a slip (the
    rail carries it again), the identifier is re-armed, so the next drop is identified afresh.

    At each drop the identifier's slip detector flags (``slipping`` rising, the first after a re-arm)
    outside a scan, v^ starts from no higher than ``drop_fraction`` x the nominal curve's peak creep v_N
    (0: off).

    The dither is smaller than extremum seeking's (0.05 km/h against 0.08) with the gain raised in
    proportion (480 against 300), so the set-point moves as fast per unit of slope: the scan makes the
    large moves, the dither only the corrections, and a smaller dither ripples the torque less."""
    name = "identified"
    defaults = {"hold_fraction": 0.98, "jump_ratio": 1.5, "rearm_s": 0.3, "drop_fraction": 1.0,
                "change_mu": 0.02, "cap_kmh": 0.7, "scan_kmh_per_s": 4.0, "scan_settle_s": 0.03,
                "scan_filter_s": 0.01, "scan_drop_mu": 0.004, "scan_flat_kmh": 0.25,
                "past_slope": 0.02, "past_s": 0.05, "rise_mu": 0.008, **ExtremumSeeking.defaults,
                "dither_kmh": 0.05, "gain": 480.0, "max_kmh": 1.6}
    ranges = {"hold_fraction": (0.1, 2.0), "jump_ratio": (0.0, 100.0), "rearm_s": (0.001, 60.0),
              "drop_fraction": (0.0, 20.0), "change_mu": (0.0, 1.0), "cap_kmh": (0.0, 30.0),
              "scan_kmh_per_s": (0.0, 1000.0), "scan_settle_s": (0.0, 10.0), "scan_filter_s": (0.0, 10.0),
              "scan_drop_mu": (0.0, 1.0), "scan_flat_kmh": (0.0, 30.0), "past_slope": (0.0, 10.0),
              "past_s": (0.0, 10.0), "rise_mu": (0.0, 1.0), **ExtremumSeeking.ranges}

    def __init__(self, vehicle, nominal_peak_creep_kmh, options=None):
        super().__init__(vehicle, nominal_peak_creep_kmh, options)
        self._was_confirmed = False
        self._was_slipping = False
        self._passing_s = 0.0
        self._rearm = False
        self._scan: _Scan | None = None
        self._past_for_s = 0.0         # how long the slope estimate has said "past a peak"
        self._mu_filtered: float | None = None      # mu^ filtered over scan_filter_s (the rise test) ...
        self._level_mu: float | None = None     # ... and its lowest value while the creep is held

    def _target_kmh(self, x: ControlInput) -> float | None:
        """hold_fraction x the confirmed peak creep, clipped to its interval (class docstring), or None."""
        peak = x.peak_creep_kmh
        if x.peak_creep_ci is not None:
            lo, hi = x.peak_creep_ci
            peak = min(max(peak, lo), hi) if math.isfinite(peak) else lo
        return self.options["hold_fraction"] * peak if math.isfinite(peak) else None

    def _rail_changed(self, x: ControlInput) -> bool:
        """The change test (class docstring), against extremum seeking's mean of mu^ (its ``torque_nm`` updates it)."""
        o = self.options
        return bool(o["change_mu"]) and self._mu_mean is not None and abs(x.mu_hat - self._mu_mean) > o["change_mu"]

    def _scan_step(self, x: ControlInput) -> float:
        """One period of the scan (class docstring); ends it when mu^ has passed its best."""
        o, scan = self.options, self._scan
        scan.time_s += x.period_s
        if scan.time_s >= o["scan_settle_s"]:
            a = x.period_s / (o["scan_filter_s"] + x.period_s)
            scan.mu = x.mu_hat if scan.mu is None else scan.mu + a * (x.mu_hat - scan.mu)
            if scan.mu > scan.best_mu:
                scan.best_mu, scan.best_kmh = scan.mu, x.creep_speed_kmh
            if scan.rise is None or scan.mu > scan.rise[0] + o["scan_drop_mu"]:
                scan.rise = (scan.mu, x.creep_speed_kmh)
            passed = scan.mu < scan.best_mu - o["scan_drop_mu"] or \
                x.creep_speed_kmh > scan.rise[1] + o["scan_flat_kmh"]
            if passed or not self.loop.limited or self.v_hat >= o["max_kmh"]:
                if passed:
                    self.v_hat = min(max(scan.best_kmh, o["min_kmh"]), o["max_kmh"])
                elif not self.loop.limited:        # the rail carries the demand: v^ just above its creep
                    self.v_hat = min(max(x.creep_speed_kmh + o["carry_kmh"], o["min_kmh"]), o["max_kmh"])
                self._scan = None
                self._mu_mean = x.mu_hat
                self._slope = 0.0
                return self.loop.torque_nm(x, self.v_hat)
            self.v_hat = min(self.v_hat + o["scan_kmh_per_s"] * x.period_s, o["max_kmh"])
        return self.loop.torque_nm(x, self.v_hat)

    def _past_a_peak(self, x: ControlInput) -> bool:
        """The dither's slope estimate, 2 LPF(demod) / a, has stayed below -``past_slope`` for ``past_s``
        while the creep loop limited the torque above ``cap_kmh`` (class docstring)."""
        o = self.options
        falling = (o["past_slope"] > 0.0 and o["dither_kmh"] > 0.0 and self.loop.limited
                   and x.creep_speed_kmh > o["cap_kmh"] and 2.0 * self._slope / o["dither_kmh"] < -o["past_slope"])
        self._past_for_s = self._past_for_s + x.period_s if falling else 0.0
        return self._past_for_s >= o["past_s"]

    def _rose(self, x: ControlInput) -> bool:
        """The rise test (class docstring): filtered mu^ above its lowest value while the creep loop holds a
        creep above ``cap_kmh`` outside a scan, by more than ``rise_mu``."""
        o = self.options
        a = x.period_s / (o["scan_filter_s"] + x.period_s)
        f = self._mu_filtered
        f = self._mu_filtered = x.mu_hat if f is None else f + a * (x.mu_hat - f)
        if not o["rise_mu"] or self._scan is not None or not self.loop.limited or x.creep_speed_kmh <= o["cap_kmh"]:
            self._level_mu = None
            return False
        self._level_mu = f if self._level_mu is None else min(self._level_mu, f)
        if f > self._level_mu + o["rise_mu"]:
            self._level_mu = None
            return True
        return False

    def torque_nm(self, x: ControlInput) -> float:
        o = self.options
        rose = self._rose(x)
        changed = rose or (self._rail_changed(x) if self._scan is None else False)
        if self._scan is None and self._past_a_peak(x):
            changed, self._past_for_s = True, 0.0
        if changed and o["cap_kmh"] > 0.0:
            self.v_hat = min(self.v_hat, max(o["cap_kmh"], o["min_kmh"]))
            if o["scan_kmh_per_s"] > 0.0:
                self._scan = _Scan()
        if x.slipping and not self._was_slipping and o["drop_fraction"] > 0.0 and self._scan is None:
            self.v_hat = min(self.v_hat, max(o["drop_fraction"] * self.nominal_peak_creep_kmh, o["min_kmh"]))
        self._was_slipping = x.slipping
        if x.confirmed and not self._was_confirmed:
            target = self._target_kmh(x)
            if target is not None and x.creep_speed_kmh >= o["jump_ratio"] * target:
                self.v_hat = min(max(target, o["min_kmh"]), o["max_kmh"])
                self._scan = None
        self._was_confirmed = x.confirmed
        torque = self._scan_step(x) if self._scan is not None else super().torque_nm(x)
        self._passing_s = self._passing_s + x.period_s if x.slipping and not self.loop.limited else 0.0
        if self._passing_s >= o["rearm_s"]:
            self._rearm, self._passing_s, self._was_confirmed = True, 0.0, False
        return torque

    @property
    def wants_rearm(self) -> bool:
        r, self._rearm = self._rearm, False
        return r
