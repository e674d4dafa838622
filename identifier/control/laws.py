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
``identified``        extremum seeking with a drop to half the set-point held and a climb at each change of rail
                      mu^ shows (what the law measures: ``blind`` = 1 runs it so, the bench's ablation), and
                      options that act on what the TCU learns of the rail (its peak estimate,
                      identifier/peak_estimate.py), all off by default: measured, none helped (the class).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..peak_estimate import prior_peak_creep_quantile_kmh
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
        self.max_now = self.options["max_kmh"]     # the set-point's bound this period (``Identified``: its ceiling)

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
        self.v_hat = min(max(self.v_hat, o["min_kmh"]), self.max_now)
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
    """Extremum seeking placed by what the TCU learns of the rail (module docstring): its peak estimate
    (identifier/peak_estimate.py: the current rail's peak creep v_p with a 90 % interval [lo, hi], every period,
    ``x.estimate``) can lift, cap or move its set-point (options, below, off by default: measured, none helped);
    no default is a rail family's extreme.

    **The estimate's creep and bound.**  With the estimate's curve mu = mu_p h(v / v_p) and h(x) = h(1 / x) (its
    k = 1 shape), min over v_p in [lo, hi] of h(v / v_p) is largest at v* = sqrt(lo hi): the creep that maximises
    the lower bound of mu over the interval.  The bound 2 ``risk_margin`` lo keeps the chance of passing twice the
    peak creep below the interval's 5 % (``risk_margin`` 0.9 leaves room for the dither and the loop's overshoot).
    An estimate is of the current rail when it dates its change of rail no earlier than ``stale_s`` before the
    last change the law acted on; ``blind`` = 1 withholds it (the bench's ablation).  An estimate is *narrow*
    when hi <= ``ceiling_width`` lo (0, the default: never).

    **A change of rail** (mu^ leaves its mean, extremum seeking's first-order filter of ``filter_s``, by more than
    ``change_mu``, up or down, while the creep loop and not the demand sets the torque (``change_limited``: a move
    of the demand moves mu^ too) and after ``startup_s``): the set-point drops to ``drop_ratio`` x the set-point
    held (what the law measured, with or without the estimate: a rail whose peak creep lies above half the creep
    held then stays out of macro-slip with no estimate at all; ``cap_kmh`` > 0 replaces it by a constant) and,
    ``scan_settle_s`` later, climbs at ``scan_kmh_per_s`` while mu^ (filtered over ``scan_filter_s``) keeps rising;
    once it has fallen ``scan_drop_mu`` below the best seen (or risen less than that over ``scan_flat_kmh``), the
    set-point returns to the creep where the best was seen and extremum seeking takes over from there.  The scan
    also ends when the demand, not the creep loop, limits the torque.  During a scan the change test is off: the
    scan itself moves mu^.

    **What the estimate adds** (all off with ``blind``).  An estimate acts once it has dated its change of rail
    ``settle_s`` ago (a change it has only just dated rests on a handful of samples of a blend of two rails).
    By default, nothing: every use measured either cost eta_low or added macro-slip on the default rail family
    (docs/design/control.md, 2026-11-29), so ``identified`` runs as ``blind`` unless an option turns one on.
    **The lift** (``lift`` 1; off: with or without the guards below it added macro-slip to runs ``blind`` held,
    for next to no eta_low, docs/design/control.md, issue 50).  While the creep loop, not the demand, has set the torque
    for ``settle_s`` (so the estimate has seen the rail at the creep held, and dated a change the demand hid)
    and the estimate's interval lies above the set-point (lo > v^: the peak is above it with 95 %), the
    set-point goes up to lo at once (``lift`` 2: to sqrt(lo x median); ``lift_kmh_per_s`` > 0: at that rate;
    ``lift_width`` > 0: only when hi <= ``lift_width`` lo); the climb and the dither carry on from there.
    ``lift_ratio`` > 1: only when lo >= ``lift_ratio`` v^ (an estimate whose low end sits just above the creep held
    says only that mu^ still rises there; lifting to it each period ratchets the creep up the rising branch and
    past the peak).  ``lift_steady_mu`` > 0: only while mu^ is not falling (no more than that below extremum seeking's mean of it: a
    rail blending into a worse one during a transition drags mu^ down for up to a second, and the estimate of that
    blend, dated after the change began, may still put the peak above the creep held).
    ``lift_hold_s`` > 0: for that long after a lift the change, rise and past-a-peak tests are off and restart
    from the mu^ the lifted creep gives (the lift's own step moves mu^ up the rising branch, which the rise test
    otherwise reads as a better rail and answers by halving the set-point).  It
    never lowers the creep, and it uses the side of the interval a calibrated estimate gets wrong 5 % of the
    time.  The other uses measured (each cost eta_low or added nothing on rails that change, where the estimate
    is narrow and wrong too often) stay as options, off by default too: the
    ceiling (while hi <= ``ceiling_width`` lo, the bound caps the set-point; 0: off), the jump (the first
    estimate of the new rail with hi <= ``jump_width`` lo moves the set-point to its centre, ``centre_median`` 1:
    its median, 0: v*; never above the bound; 0: off) and the tracking towards that centre at
    ``track_kmh_per_s`` while it stays so narrow, the new rail's bound (``new_rail_bound`` 1: once per change of
    rail, the first narrow estimate lowers the set-point to its bound), the cap at the interval's high end
    (``probe_hi`` 1), and ``recall`` (1: back on a better rail, mu^ up, the set-point goes to the median of the
    rail left at the last drop, as its last narrow estimate knew it, instead of dropping).

    **Past a peak**: when the dither's slope estimate 2 LPF(demod) / a stays below -``past_slope`` (per km/h) for
    ``past_s`` while the creep loop holds a creep above the bound, the set-point drops and climbs as at a change of
    rail, unless a narrow estimate puts the peak above the creep held.  **A better rail**: while the creep loop
    holds a creep above the bound outside a scan, mu^ filtered over ``scan_filter_s`` rising more than ``rise_mu``
    above its lowest value since then drops the set-point and climbs as at a change of rail (0: off).  Both were
    shown necessary by the macro-slips docs/design/control.md measures.

    **A confirmed curve** whose peak creep the creep has passed ``jump_ratio``-fold moves the set-point to
    ``hold_fraction`` x that peak creep (clipped to its 90 % interval).  Once the demand has passed through for
    ``rearm_s`` after a slip, the identifier is re-armed.  At each drop the slip detector flags outside a scan,
    v^ starts from no higher than ``drop_fraction`` x the nominal curve's peak creep (0, the default: off).

    The dither is smaller than extremum seeking's (0.05 km/h against 0.08) with the gain raised in proportion (480
    against 300): the scan and the estimate make the large moves, the dither the corrections."""
    name = "identified"
    defaults = {"hold_fraction": 0.98, "jump_ratio": 1.5, "rearm_s": 0.3, "drop_fraction": 0.0,
                "change_mu": 0.02, "cap_kmh": 0.0, "scan_kmh_per_s": 4.0, "scan_settle_s": 0.03,
                "scan_filter_s": 0.01, "scan_drop_mu": 0.004, "scan_flat_kmh": 0.25,
                "past_slope": 0.02, "past_s": 0.05, "rise_mu": 0.008, "drop_ratio": 0.5, "settle_s": 0.1, "centre_median": 1, "new_rail_bound": 0, "recall": 0, "lift": 0, "lift_hold_s": 0.0, "lift_steady_mu": 0.0, "lift_ratio": 1.0, "lift_kmh_per_s": 0.0, "lift_width": 0.0, "probe_hi": 0, "risk_margin": 0.9, "jump_width": 0.0,
                "ceiling_width": 0.0, "stale_s": 0.1, "startup_s": 0.2, "new_rail_s": 0.0, "track_kmh_per_s": 1.0, "track_band": 0.1, "change_limited": 1, "blind": 0, **ExtremumSeeking.defaults,
                "dither_kmh": 0.05, "gain": 480.0}
    ranges = {"hold_fraction": (0.1, 2.0), "jump_ratio": (0.0, 100.0), "rearm_s": (0.001, 60.0),
              "risk_margin": (0.1, 1.0), "jump_width": (0.0, 100.0), "ceiling_width": (0.0, 1000.0),
              "stale_s": (0.0, 10.0), "startup_s": (0.0, 60.0), "new_rail_s": (0.0, 60.0), "track_kmh_per_s": (0.0, 100.0),
              "track_band": (0.0, 10.0), "change_limited": (0, 1),
              "blind": (0, 1),
              "drop_fraction": (0.0, 20.0), "change_mu": (0.0, 1.0), "cap_kmh": (0.0, 30.0), "drop_ratio": (0.0, 1.0), "settle_s": (0.0, 10.0),
              "centre_median": (0, 1), "new_rail_bound": (0, 1), "recall": (0, 1), "lift": (0, 2), "lift_hold_s": (0.0, 10.0), "lift_steady_mu": (0.0, 1.0), "lift_ratio": (1.0, 100.0), "lift_kmh_per_s": (0.0, 1000.0), "lift_width": (0.0, 1000.0), "probe_hi": (0, 1),
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
        o = self.options
        # the bound at a change of rail: what the estimate allows with no sample of the new rail yet (its prior)
        self.cap_kmh = o["cap_kmh"] or 2.0 * o["risk_margin"] * prior_peak_creep_quantile_kmh(0.05)
        self.cap_kmh = max(self.cap_kmh, o["min_kmh"])
        self._changed_t_s = -math.inf       # the last change of rail the law acted on
        self._jumped = False
        self._bounded = True                # the new rail's estimate has bounded the set-point (once per change)
        self._limited_for_s = 0.0            # how long the creep loop, not the demand, has set the torque
        self._left: tuple[float, float] | None = None   # (median, bound) of the rail left at the last drop
        self._lifted_t_s = -math.inf        # the last lift

    def _target_kmh(self, x: ControlInput) -> float | None:
        """hold_fraction x the confirmed peak creep, clipped to its interval (class docstring), or None."""
        peak = x.peak_creep_kmh
        if x.peak_creep_ci is not None:
            lo, hi = x.peak_creep_ci
            peak = min(max(peak, lo), hi) if math.isfinite(peak) else lo
        return self.options["hold_fraction"] * peak if math.isfinite(peak) else None

    def _rail_changed(self, x: ControlInput) -> bool:
        """The change test (class docstring), against extremum seeking's mean of mu^ (its ``torque_nm`` updates it),
        only while the creep loop, not the demand, set the torque (a move of the demand moves mu^ too) and not in
        the observer's first ``startup_s``."""
        o = self.options
        return bool(o["change_mu"]) and self._mu_mean is not None \
            and (self.loop.limited or not o["change_limited"]) and x.t_s >= o["startup_s"] and abs(x.mu_hat - self._mu_mean) > o["change_mu"]

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
            if passed or not self.loop.limited or self.v_hat >= self.max_now:
                if passed:
                    self.v_hat = min(max(scan.best_kmh, o["min_kmh"]), self.max_now)
                elif not self.loop.limited:        # the rail carries the demand: v^ just above its creep
                    self.v_hat = min(max(x.creep_speed_kmh + o["carry_kmh"], o["min_kmh"]), self.max_now)
                self._scan = None
                self._mu_mean = x.mu_hat
                self._slope = 0.0
                return self.loop.torque_nm(x, self.v_hat)
            self.v_hat = min(self.v_hat + o["scan_kmh_per_s"] * x.period_s, self.max_now)
        return self.loop.torque_nm(x, self.v_hat)

    def _past_a_peak(self, x: ControlInput) -> bool:
        """The dither's slope estimate, 2 LPF(demod) / a, has stayed below -``past_slope`` for ``past_s``
        while the creep loop limited the torque above ``cap_kmh`` (class docstring)."""
        o = self.options
        falling = (o["past_slope"] > 0.0 and o["dither_kmh"] > 0.0 and self.loop.limited
                   and x.creep_speed_kmh > self.cap_kmh and 2.0 * self._slope / o["dither_kmh"] < -o["past_slope"])
        self._past_for_s = self._past_for_s + x.period_s if falling else 0.0
        return self._past_for_s >= o["past_s"]

    def _rose(self, x: ControlInput) -> bool:
        """The rise test (class docstring): filtered mu^ above its lowest value while the creep loop holds a
        creep above ``cap_kmh`` outside a scan, by more than ``rise_mu``."""
        o = self.options
        a = x.period_s / (o["scan_filter_s"] + x.period_s)
        f = self._mu_filtered
        f = self._mu_filtered = x.mu_hat if f is None else f + a * (x.mu_hat - f)
        if not o["rise_mu"] or self._scan is not None or not self.loop.limited or x.creep_speed_kmh <= self.cap_kmh:
            self._level_mu = None
            return False
        self._level_mu = f if self._level_mu is None else min(self._level_mu, f)
        if f > self._level_mu + o["rise_mu"]:
            self._level_mu = None
            return True
        return False

    def _estimate(self, x: ControlInput):
        """The identifier's estimate of the current rail (``x.estimate``) when the law may act on it: not blind,
        and dated (its change of rail) no earlier than ``stale_s`` before the last change the law acted on."""
        e = x.estimate
        if self.options["blind"] or e is None:
            return None
        if e.since_step * x.period_s < self._changed_t_s - self.options["stale_s"]:
            return None
        if (e.step - e.since_step) * x.period_s < self.options["settle_s"]:     # a change it has only just dated
            return None
        return e

    def _bounds(self, e) -> tuple[float, float] | None:
        """(the creep maximising the lower bound of mu over the estimate's peak-creep interval [lo, hi], the
        creep bound 2 risk_margin lo) from estimate ``e``.  With mu = mu_p h(v / v_p) and h(x) = h(1 / x) (the
        estimate's k = 1 shape), min over v_p in [lo, hi] of h(v / v_p) is largest at v = sqrt(lo hi); the bound
        keeps P(v > 2 v_p) below the interval's 5 % (the ``risk_margin`` to spare for the loop's overshoot)."""
        lo, hi = e.peak_creep_ci
        if not (math.isfinite(lo) and math.isfinite(hi) and lo > 0.0):
            return None
        bound = 2.0 * self.options["risk_margin"] * lo
        best = e.peak_creep_kmh if self.options["centre_median"] else math.sqrt(lo * hi)
        return min(best, bound), bound

    def torque_nm(self, x: ControlInput) -> float:
        o = self.options
        e = self._estimate(x)
        b = self._bounds(e) if e is not None else None
        lo_hi = e.peak_creep_ci if b is not None else None
        narrow = b is not None and lo_hi[1] <= o["ceiling_width"] * lo_hi[0]
        # the ceiling: the estimate's creep bound while the rail is new to it or once its interval is narrow
        # enough to mean it (a wide interval of a rail the demand carries says little), else max_kmh
        self.max_now = max(min(o["max_kmh"], b[1]), o["min_kmh"]) \
            if b is not None and (narrow or x.t_s - self._changed_t_s < o["new_rail_s"]) else o["max_kmh"]
        if b is not None and o["probe_hi"]:          # never probe above the interval's upper end
            self.max_now = max(min(self.max_now, lo_hi[1]), o["min_kmh"])
        # (only once the creep loop has set the torque for settle_s: the estimate has then seen the rail at the
        # creep the law holds, and dated a change the demand hid)
        self._limited_for_s = self._limited_for_s + x.period_s if self.loop.limited else 0.0
        if b is not None and o["lift"] and self._limited_for_s >= o["settle_s"] and lo_hi[0] > o["lift_ratio"] * self.v_hat \
                and (not o["lift_width"] or lo_hi[1] <= o["lift_width"] * lo_hi[0]) \
                and (not o["lift_steady_mu"] or self._mu_mean is None or x.mu_hat >= self._mu_mean - o["lift_steady_mu"]):
            # the estimate is sure (95 %) the peak lies above the set-point: up to its low end at once (a climb
            # carries on from there; the dither, not a climb, would take seconds)
            up = math.sqrt(lo_hi[0] * e.peak_creep_kmh) if o["lift"] > 1 else lo_hi[0]
            if o["lift_kmh_per_s"] > 0.0:        # at a rate: an estimate of a blend of two rails lasts a few tens of ms
                up = min(up, self.v_hat + o["lift_kmh_per_s"] * x.period_s)
            if min(up, self.max_now) > self.v_hat:
                self._lifted_t_s = x.t_s
            self.v_hat = max(min(up, self.max_now), self.v_hat)
        rose = self._rose(x)
        moved = self._rail_changed(x) if self._scan is None else False
        if x.t_s - self._lifted_t_s < o["lift_hold_s"]:
            # the lift's own step moves mu^ (the creep climbs the rising branch): not a change of rail, nor a peak
            # passed; the tests start again from the mu^ the lifted creep gives
            rose = moved = False
            self._level_mu, self._past_for_s = None, 0.0
            self._mu_mean, self._slope = x.mu_hat, 0.0
        changed = rose or moved
        up = rose or (moved and x.mu_hat > self._mu_mean)      # a better rail (a patch's end) or a worse one
        if moved and not up and narrow:
            self._left = (e.peak_creep_kmh, b[1])               # the rail left, as the estimate knew it
        if self._scan is None and self._past_a_peak(x):
            # not past the peak when a narrow estimate puts it above the creep
            if not (narrow and x.creep_speed_kmh < e.peak_creep_kmh):
                changed = True
            self._past_for_s = 0.0
        if changed:
            # down to a fraction of the set-point held (what the law measured: blind or not), or, given it,
            # ``cap_kmh`` (with ``new_rail_bound``, the estimate of the new rail bounds it further once it has
            # dated the change: below)
            cap = o["cap_kmh"] if o["cap_kmh"] else max(o["drop_ratio"] * self.v_hat, self.cap_kmh) \
                if o["drop_ratio"] > 0.0 else max(self.cap_kmh, b[1]) if narrow else self.cap_kmh   # 0: as of 2026-11-28
            self._changed_t_s, self._jumped, self._bounded = x.t_s, False, False
            if up and o["recall"] and self._left is not None:
                # back to a better rail: the one left at the last drop, as the estimate knew it (its median, never
                # above its bound); the dither and the tests above correct it if this rail is another one
                cap = min(self._left[0], self._left[1])
                self.v_hat = max(cap, o["min_kmh"])
                self._left = None
            self.v_hat = min(self.v_hat, cap)
            if o["scan_kmh_per_s"] > 0.0:
                self._scan = _Scan()
        # the estimate of the new rail (dated at or after the change), narrow enough to mean it: its creep bound
        # caps the set-point once per change of rail, whether climbing or not
        if b is not None and o["new_rail_bound"] and not self._bounded and e.since_step * x.period_s >= self._changed_t_s - o["stale_s"] \
                and x.t_s - self._changed_t_s < o["new_rail_s"] + o["stale_s"] + 1.0 and narrow:
            self._bounded = True
            if self.v_hat > b[1]:
                self.v_hat = max(b[1], o["min_kmh"])
        # the estimate of the new rail narrow enough: to the creep it says is best, once per change of rail
        if b is not None and not self._jumped and lo_hi[1] <= o["jump_width"] * lo_hi[0] \
                and (self._scan is not None or x.t_s - self._changed_t_s < o["stale_s"] + 1.0):
            self._jumped = True
            self.v_hat = min(max(b[0], o["min_kmh"]), self.max_now)
            self._scan = None
            self._mu_mean, self._slope = x.mu_hat, 0.0
        # holding a creep far from the one a narrow estimate says is best: move towards it (extremum seeking's
        # dither still corrects; the estimate's interval, not the dither's slope, sets where it goes)
        elif b is not None and self._scan is None and o["track_kmh_per_s"] > 0.0 and self.loop.limited \
                and lo_hi[1] <= o["jump_width"] * lo_hi[0] and abs(self.v_hat - b[0]) > o["track_band"] * b[0]:
            step = o["track_kmh_per_s"] * x.period_s
            self.v_hat += max(min(b[0] - self.v_hat, step), -step)
        if x.slipping and not self._was_slipping and o["drop_fraction"] > 0.0 and self._scan is None:
            self.v_hat = min(self.v_hat, max(o["drop_fraction"] * self.nominal_peak_creep_kmh, o["min_kmh"]))
        self._was_slipping = x.slipping
        if x.confirmed and not self._was_confirmed:
            target = self._target_kmh(x)
            if target is not None and x.creep_speed_kmh >= o["jump_ratio"] * target:
                self.v_hat = min(max(target, o["min_kmh"]), self.max_now)
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
