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
``identified``        acts on the identifier's live curve: holds the creep at the lower end of the 90 %
                      peak-creep interval once the curve is confirmed, probes upward only as far as the
                      interval's upper end while it is not, and starts from the nominal peak creep.
"""
from __future__ import annotations

import math

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
    not the demand, limits the torque; v^ then follows the measured creep from above).  The dither's phase is
    shifted by ``lag_s``, the observer's lag behind the true mu (2 / its pole)."""
    name = "extremum_seeking"
    defaults = {"dither_kmh": 0.08, "dither_hz": 8.0, "gain": 300.0, "filter_s": 0.1, "lag_s": 0.004,
                "min_kmh": 0.2, "max_kmh": 12.0, **_LOOP_DEFAULTS}
    ranges = {"dither_kmh": (0.0, 2.0), "dither_hz": (0.1, 200.0), "gain": (0.0, 1e5), "filter_s": (0.001, 10.0),
              "lag_s": (0.0, 1.0), "min_kmh": (0.0, 30.0), "max_kmh": (0.1, 30.0), **_LOOP_RANGES}

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
        self._mu_mean += a * (x.mu_hat - self._mu_mean)                 # high pass: mu^ minus its mean
        demod = (x.mu_hat - self._mu_mean) * math.sin(phase - 2 * math.pi * o["dither_hz"] * o["lag_s"])
        self._slope += a * (demod - self._slope)                          # low pass of the demodulated slope
        if self.loop.limited:
            self.v_hat += o["gain"] * self._slope * x.period_s
        else:                       # the demand limits: keep v^ just above the creep it carries
            self.v_hat = max(min(self.v_hat, x.creep_speed_kmh + 2 * o["dither_kmh"]), o["min_kmh"])
        self.v_hat = min(max(self.v_hat, o["min_kmh"]), o["max_kmh"])
        return self.loop.torque_nm(x, self.v_hat + o["dither_kmh"] * math.sin(phase))


class Identified(Controller):
    """Acts on the identifier's curve (module docstring).  While the creep loop (not the demand) limits the
    torque:

    - a confirmed curve (or one given up with a best estimate): v* = ``hold_fraction`` x its peak creep, kept
      inside the 90 % peak-creep interval (its lower end when the curve's own peak lies below it);
    - nothing confirmed: v* climbs at ``probe_kmh_per_s`` from ``start_fraction`` x the nominal peak creep,
      never past the latest interval's upper end, and steps back to the best creep seen once mu^ (low-passed
      over ``filter_s``) has fallen ``drop_mu`` below the best it reached while the creep rose past it by
      ``creep_step_kmh`` (the data show the peak passed), holding there ``repeek_s`` before it climbs again;
    - once the demand has passed through for ``rearm_s`` after a slip, or mu^ has left the confirmed curve's
      peak interval by ``stale_mu`` (above it: the rail got better; below it while holding the peak: the curve
      does not describe this rail), the identifier is re-armed (a new drop finds it fresh) and v* returns to
      its start (from a stale curve: probes on from the creep held).
    """
    name = "identified"
    defaults = {"hold_fraction": 0.98, "probe_kmh_per_s": 3.0, "rearm_s": 0.3, "start_fraction": 1.0,
                "max_kmh": 12.0, "filter_s": 0.05, "drop_mu": 0.004, "creep_step_kmh": 0.05, "repeek_s": 2.0,
                "stale_mu": 0.01, **_LOOP_DEFAULTS}
    ranges = {"hold_fraction": (0.1, 2.0), "probe_kmh_per_s": (0.0, 100.0), "rearm_s": (0.001, 60.0),
              "start_fraction": (0.05, 10.0), "max_kmh": (0.1, 30.0), "filter_s": (0.0, 1.0), "drop_mu": (0.0, 1.0),
              "creep_step_kmh": (0.0, 10.0), "repeek_s": (0.0, 600.0), "stale_mu": (0.0, 1.0), **_LOOP_RANGES}

    def __init__(self, vehicle, nominal_peak_creep_kmh, options=None):
        super().__init__(vehicle, nominal_peak_creep_kmh, options)
        self.loop = CreepLoop(vehicle, self.options["bandwidth_rad_s"], self.options["integral_rad_s"])
        self._start = self.options["start_fraction"] * nominal_peak_creep_kmh
        self._rearm = False
        self._restart()

    def _restart(self, from_kmh: float | None = None) -> None:
        """Start afresh: v* at its start, or (a stale curve, the loop holding the creep) at ``from_kmh``, the
        creep it holds, to probe upward from there without a jump."""
        self.set_point = self._start if from_kmh is None else min(from_kmh, self._start)
        self.passed_peak = False
        self._hold_until_s = -math.inf
        self._best = (-math.inf, self.set_point)  # (mu^, creep) at the best mu^ seen while probing
        self._mu_f = None
        self._passing_s = 0.0
        self.loop.reset()

    def _target_kmh(self, x: ControlInput) -> float | None:
        """The confirmed curve's set-point (class docstring), or None."""
        if not x.confirmed:
            return None
        peak = x.peak_creep_kmh
        if x.peak_creep_ci is not None:
            lo, hi = x.peak_creep_ci
            peak = min(max(peak, lo), hi) if math.isfinite(peak) else lo
        return self.options["hold_fraction"] * peak if math.isfinite(peak) else None

    def _climb(self, x: ControlInput) -> None:
        """Hill-climb while nothing is confirmed (class docstring).  mu^ below its best by ``drop_mu`` after the
        creep rose past the best's creep: the peak was passed, step back and hold for ``repeek_s``; at a creep
        that did not rise: the rail changed under it, the best is forgotten."""
        o = self.options
        if self.passed_peak:
            if x.t_s < self._hold_until_s:
                return
            self.passed_peak = False
            self._best = (-math.inf, self.set_point)
        if self._mu_f > self._best[0]:
            self._best = (self._mu_f, x.creep_speed_kmh)
        elif self._mu_f < self._best[0] - o["drop_mu"]:
            if x.creep_speed_kmh > self._best[1] + o["creep_step_kmh"]:
                self.passed_peak = True
                self.set_point = self._best[1]
                self._hold_until_s = x.t_s + o["repeek_s"]
                return
            self._best = (self._mu_f, x.creep_speed_kmh)
        ceiling = o["max_kmh"] if x.peak_creep_ci is None else min(o["max_kmh"], x.peak_creep_ci[1])
        self.set_point = min(self.set_point + o["probe_kmh_per_s"] * x.period_s, max(ceiling, self.set_point))

    def torque_nm(self, x: ControlInput) -> float:
        o = self.options
        a = x.period_s / (o["filter_s"] + x.period_s)
        self._mu_f = x.mu_hat if self._mu_f is None else self._mu_f + a * (x.mu_hat - self._mu_f)
        target = self._target_kmh(x)
        if target is not None:
            self.set_point = target
        elif self.loop.limited:
            self._climb(x)
        torque = self.loop.torque_nm(x, self.set_point)
        self._passing_s = self._passing_s + x.period_s if x.slipping and not self.loop.limited else 0.0
        stale = (x.confirmed and x.peak_mu_ci is not None and math.isfinite(x.peak_mu_ci[0])
                 and (self._mu_f > x.peak_mu_ci[1] + o["stale_mu"]
                      or (self.loop.limited and self._mu_f < x.peak_mu_ci[0] - o["stale_mu"])))
        if self._passing_s >= o["rearm_s"] or stale:
            self._rearm = True
            self._restart(x.creep_speed_kmh if stale else None)
        return torque

    @property
    def wants_rearm(self) -> bool:
        r, self._rearm = self._rearm, False
        return r
