"""The controller interface and the creep loop every creep-holding law shares.

A controller turns what the TCU knows at one reading into the torque it commands::

    torque_nm = controller.torque_nm(x)        x: ControlInput (the reading's creep, the observer's load
                                               torque and mu^, the driver's demand, the identifier's state)

Options are checked when the controller is built (``check_options``: a bad value is one ``ValueError``
line naming the option), as the strategies' are.

``CreepLoop`` holds the measured creep speed at a set-point v* with the observer's load torque as feed
forward (the wheelset's motor-shaft equation J_eq d(omega)/dt = T - T_L; v_s = 3.6 (omega r / R_g - v_t)):

    c          = 3.6 r / R_g                                   km/h of creep per rad/s of motor speed
    e          = v* - v_s                                      creep error, km/h
    T          = T^_L + (J_eq / c) (K_p e + K_i integral(e))   so that dv_s/dt ~ K_p e (first order, pole K_p)
    T_cmd      = clip(T, 0, T_demand)                          never more than the driver asks

and integrates e only while T lies inside (0, T_demand) (conditional integration: no wind-up while the
demand, not the creep, limits the torque).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

KMH_PER_MS = 3.6


@dataclass(frozen=True)
class ControlInput:
    """What a control law sees at one reading (never the plant's truth)."""
    step: int
    t_s: float
    period_s: float
    demand_nm: float                 # the driver's demand (DriverDemand frame), motor torque
    creep_speed_kmh: float           # from the measured speeds
    load_torque_nm: float            # the observer's T^_L
    mu_hat: float                    # T^_L / torque_per_mu
    slipping: bool                   # the identifier's slip detector has fired (since its last re-arm)
    peak_creep_ci: tuple[float, float] | None = None    # the identifier's latest 90 % peak-creep interval
    peak_mu_ci: tuple[float, float] | None = None
    confirmed: bool = False          # the identifier's latest curve is confirmed (or given up with a best estimate)
    peak_creep_kmh: float = math.nan     # the peak creep of the identifier's latest curve (NaN: none yet)
    estimate: object | None = None       # the current rail's peak estimate (identifier/peak_estimate.py), or None


def check_range(options: dict, name: str, lo: float, hi: float) -> None:
    value = options[name]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not lo <= value <= hi:
        raise ValueError(f"{name} must be a number in [{lo:g}, {hi:g}], got {value!r}")


class Controller:
    """A control law.  ``defaults``: its options with their defaults; ``ranges``: (lo, hi) per option."""

    name = "?"
    defaults: dict = {}
    ranges: dict = {}

    def __init__(self, vehicle, nominal_peak_creep_kmh: float, options: dict | None = None):
        self.options = self.checked({**self.defaults, **(options or {})})
        self.vehicle = vehicle
        self.nominal_peak_creep_kmh = nominal_peak_creep_kmh

    @classmethod
    def checked(cls, options: dict) -> dict:
        for key in options:
            if key not in cls.defaults:
                raise ValueError(f"unknown option {key!r} (known: {', '.join(cls.defaults) or 'none'})")
        for key, (lo, hi) in cls.ranges.items():
            check_range(options, key, lo, hi)
        return options

    def torque_nm(self, x: ControlInput) -> float:
        raise NotImplementedError

    @property
    def wants_rearm(self) -> bool:
        """True once, when the law asks the identifier to start afresh (a new drop may come)."""
        return False


class CreepLoop:
    """Holds the creep at a set-point (module docstring)."""

    def __init__(self, vehicle, bandwidth_rad_s: float, integral_rad_s: float):
        self.gain_nm_per_kmh = vehicle.equivalent_inertia_kgm2 / (KMH_PER_MS * vehicle.wheel_radius_m
                                                                   / vehicle.gear_ratio)
        self.k_p = bandwidth_rad_s
        self.k_i = integral_rad_s * bandwidth_rad_s
        self.integral = 0.0
        self.limited = False          # the last command was the creep loop's, below the demand

    def torque_nm(self, x: ControlInput, set_point_kmh: float) -> float:
        e = set_point_kmh - x.creep_speed_kmh
        t = x.load_torque_nm + self.gain_nm_per_kmh * (self.k_p * e + self.k_i * self.integral)
        if 0.0 < t < x.demand_nm:
            self.integral += e * x.period_s
        self.limited = t < x.demand_nm
        return min(max(t, 0.0), x.demand_nm)

    def reset(self) -> None:
        self.integral = 0.0
