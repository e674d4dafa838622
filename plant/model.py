"""The wheelset-rail plant in CasADi, stepped at a fixed integration step.

States: motor angular speed ``omega_m`` (rad/s) and train speed ``v_t`` (m/s).

    v_s   = 3.6 * (omega_m / R_g * r - v_t)                 creep speed, km/h (eq. 1)
    mu    = curve(v_s, v_t)   NFCC-0 before t_f, the fault curve after (exponential curves ignore
                              v_t; Polach's law uses it through the creepage, plant/friction.py)
    T_L   = mu * T_W * g * r / (eta * R_g)                  load torque at the motor shaft
    J_eq * d(omega_m)/dt = T_e - T_L                        (Appendix A)
    M * dv_t/dt = mu * T_W * g + (n_driven - 1) * mu_req * T_W * g - R(v_t)

With a demand profile (plant/rail.py), the other driven axles hold the driver's demand mu_d(t) in place
of mu_req (ideal axles: they are not the wheelset under test).

One call of the compiled CasADi ``Function`` advances one *exchange period* with several RK4
sub-steps, so Python pays its call overhead once per period rather than once per sub-step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import casadi as ca
import numpy as np

from .friction import FrictionCurve, PolachCurve
from .params import KMH_PER_MS, WheelsetParams
from .rail import DemandProfile, RailSchedule


@dataclass(frozen=True)
class PlantConfig:
    params: WheelsetParams
    normal_curve: FrictionCurve          # NFCC-0
    fault_curve: FrictionCurve | PolachCurve   # FFCC, active from fault_time_s
    mu_required: float                   # demanded adhesion before the fault
    fault_time_s: float
    initial_train_speed_ms: float
    integration_step_s: float            # h, RK4 step
    exchange_period_s: float             # one plant call (= one bus exchange)
    rail: RailSchedule | None = None     # the rail along the run (replaces normal/fault curves when set)
    demand: DemandProfile | None = None  # the driver's demand: the other axles hold it (module docstring)

    @property
    def cleaning_inputs(self) -> int:
        """How many recovering rail segments feed the period step their cleaned fraction rho."""
        return len(self.rail.recovery) if self.rail is not None else 0

    @property
    def substeps(self) -> int:
        n = self.exchange_period_s / self.integration_step_s
        if abs(n - round(n)) > 1e-9 or round(n) < 1:
            raise ValueError("exchange_period_s must be a whole multiple of integration_step_s")
        return int(round(n))


@dataclass(frozen=True)
class PlantState:
    """True plant state at time t_s (never shown to the identifier)."""

    t_s: float
    motor_speed_rad_s: float
    train_speed_ms: float
    creep_speed_kmh: float
    mu: float
    load_torque_nm: float
    torque_nm: float
    fault_active: bool


def creep_speed_kmh(p: WheelsetParams, motor_speed_rad_s, train_speed_ms):
    """v_s = omega_w * r - v_t, in km/h."""
    return KMH_PER_MS * (motor_speed_rad_s / p.gear_ratio * p.wheel_radius_m - train_speed_ms)


def build_dynamics(cfg: PlantConfig, window: tuple[int, int] | None = None) -> ca.Function:
    """f(x, T_e, t[, rho]) -> (dx/dt, mu, v_s_kmh): the continuous-time model as a CasADi Function
    (``rho``: the cleaned fractions of recovering rail segments, when there are any; ``window``: only
    these rail segments, ``RailSchedule.mu_casadi``)."""
    x = ca.SX.sym("x", 2)
    torque = ca.SX.sym("torque_nm")
    t = ca.SX.sym("t_s")
    extra = [ca.SX.sym("rho", cfg.cleaning_inputs)] if cfg.cleaning_inputs else []
    return ca.Function("wheelset_dynamics", [x, torque, t, *extra],
                       list(dynamics(cfg, x, torque, t, *extra, window=window)),
                       ["x", "torque_nm", "t_s", *(["rho"] if extra else [])], ["dx", "mu", "creep_speed_kmh"])


def dynamics(cfg: PlantConfig, x, torque, t, cleaned=None, window=None):
    """(dx/dt, mu, v_s_kmh) as CasADi expressions.  The numbers in ``cfg`` (params, curves, fault
    time, mu_required) may themselves be CasADi symbols: the FMU export (plant/fmu) builds its
    parameterised model from this same function."""
    p = cfg.params
    omega_m, v_t = x[0], x[1]
    v_s = creep_speed_kmh(p, omega_m, v_t)
    if cfg.rail is not None:
        mu = cfg.rail.mu_casadi(v_s, v_t, t, cleaned, window)
    else:
        mu = ca.if_else(t >= cfg.fault_time_s, cfg.fault_curve.mu_casadi(v_s, v_t),
                        cfg.normal_curve.mu_casadi(v_s, v_t))
    load_torque = mu * p.torque_per_mu_nm
    other_mu = cfg.mu_required if cfg.demand is None else cfg.demand.casadi(t)
    other_axles_n = (p.driven_axles - 1) * other_mu * p.normal_force_n
    d_omega = (torque - load_torque) / p.equivalent_inertia_kgm2
    d_v = (mu * p.normal_force_n + other_axles_n - p.running_resistance_n(v_t)) / p.train_mass_kg
    return ca.vertcat(d_omega, d_v), mu, v_s


def rk4_step(f, x, torque, t, h):
    """One RK4 step of ``dx = f(x, torque, t)`` from t to t + h, torque held.

    The rail condition is held over a sub-step (all four stages see its start time), so the
    fault switches exactly at a sub-step boundary instead of leaking into a k4 stage.
    Shared by the loop's plant and the FMU export (plant/fmu), so the two cannot drift.
    """
    k1 = f(x, torque, t)
    k2 = f(x + h / 2 * k1, torque, t)
    k3 = f(x + h / 2 * k2, torque, t)
    k4 = f(x + h * k3, torque, t)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def build_period_step(cfg: PlantConfig, window: tuple[int, int] | None = None) -> ca.Function:
    """F(x, T_e, t0[, rho]) -> (x, mu, v_s_kmh) at t0 + exchange_period: ``substeps`` RK4 steps, torque
    (and the rail's cleaned fractions rho, when it has recovering segments) held; ``window``: the rail
    segments (lo, hi) only, for periods where the others weigh nothing (``RailSchedule.window_at``)."""
    f = build_dynamics(cfg, window)
    x0 = ca.SX.sym("x", 2)
    torque = ca.SX.sym("torque_nm")
    t0 = ca.SX.sym("t0_s")
    extra = [ca.SX.sym("rho", cfg.cleaning_inputs)] if cfg.cleaning_inputs else []
    h = cfg.integration_step_s
    x = x0
    for i in range(cfg.substeps):
        x = rk4_step(lambda x_, u_, t_: f(x_, u_, t_, *extra)[0], x, torque, t0 + i * h, h)
    _, mu, v_s = f(x, torque, t0 + cfg.substeps * h, *extra)
    return ca.Function("wheelset_period_step", [x0, torque, t0, *extra], [x, mu, v_s],
                       ["x0", "torque_nm", "t0_s", *(["rho"] if extra else [])], ["x", "mu", "creep_speed_kmh"])


def equilibrium(cfg: PlantConfig) -> tuple[np.ndarray, float]:
    """Initial state at the creep where NFCC-0 gives mu_required, and the torque that holds it.

    The held torque includes the share that accelerates the wheelset with the train, so the creep
    speed stays constant until the fault.
    """
    p = cfg.params
    first = cfg.rail.segments[0].curve if cfg.rail is not None else cfg.normal_curve
    v_s0_kmh = first.creep_for_mu(cfg.mu_required)
    v_t0 = cfg.initial_train_speed_ms
    omega_m0 = (v_t0 + v_s0_kmh / KMH_PER_MS) * p.gear_ratio / p.wheel_radius_m
    accel0 = (p.driven_axles * cfg.mu_required * p.normal_force_n - p.running_resistance_n(v_t0)) / p.train_mass_kg
    torque0 = cfg.mu_required * p.torque_per_mu_nm + p.equivalent_inertia_kgm2 * p.gear_ratio / p.wheel_radius_m * accel0
    return np.array([omega_m0, v_t0]), float(torque0)


def train_speed_before_fault(p: WheelsetParams, mu_required: float, initial_train_speed_ms: float,
                             t_s: float, step_s: float = 0.01) -> float:
    """Train speed (m/s) at ``t_s`` before the fault, from the equilibrium start: every driven axle holds
    ``mu_required`` (the faulty one too, its creep held by the equilibrium torque), so

        M dv_t/dt = n_driven * mu_required * T_W * g - R(v_t)

    integrated by RK4 at ``step_s`` (``mu_required`` may be a numpy array: one speed per value).  The
    plant's own creep drifts by ~1e-5 km/h before the fault as the running resistance grows; its train
    speed at the fault agrees with this to 1e-6 m/s (tests/test_families.py).
    Polach curves take their truth at this speed at the fault time (hil/config.py, plant/families.py).
    """
    n = max(int(math.ceil(t_s / step_s)), 1) if t_s > 0 else 0
    v = initial_train_speed_ms + 0.0 * mu_required       # numpy arrays of mu_required work too
    if n == 0:
        return v
    h = t_s / n
    drive = p.driven_axles * mu_required * p.normal_force_n

    def accel(v_):
        return (drive - p.running_resistance_n(v_)) / p.train_mass_kg

    for _ in range(n):
        k1 = accel(v)
        k2 = accel(v + h / 2 * k1)
        k3 = accel(v + h / 2 * k2)
        k4 = accel(v + h * k3)
        v += h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return v


def bind_buffer(fn: ca.Function, args, results):
    """``fn.buffer()`` bound to preallocated numpy arrays: returns (buffer, evaluate).

    The caller must keep the buffer and every array alive as long as it evaluates (CasADi reads and
    writes them through raw pointers).
    """
    buffer, evaluate = fn.buffer()
    for i, arr in enumerate(args):
        buffer.set_arg(i, memoryview(arr))
    for i, arr in enumerate(results):
        buffer.set_res(i, memoryview(arr))
    return buffer, evaluate


class Plant(Protocol):
    """What a run needs of a plant: the CasADi ``WheelsetPlant``, ``plant.reality.RealityPlant`` and
    ``plant.fmu_plant.FmuPlant`` all fit.  ``step`` advances one exchange period holding the torque."""

    step_index: int
    state: PlantState

    @property
    def t_s(self) -> float: ...

    def reset(self) -> PlantState: ...

    def step(self, torque_nm: float) -> PlantState: ...


#: a period's window of rail segments reaches this far (s) past either end (``RailSchedule.window_at``)
WINDOW_MARGIN_S = 1e-6


class WheelsetPlant:
    """Fixed-step wheelset-rail plant: ``step(torque_nm)`` advances one exchange period.

    The CasADi function is called through ``Function.buffer()`` on preallocated numpy arrays
    (a fraction of the cost of a call with numpy arguments; docs/design/identifier.md).  The arrays and the
    buffers are attributes of the plant, so they live exactly as long as it does: if either were
    garbage-collected while the other is used, CasADi would read freed memory.

    On a rail of several segments each period is stepped by a function of only the segments that weigh
    in it (``RailSchedule.window_at``): the same numbers to the bit, without evaluating every segment's
    curve at every RK4 stage of the run.  Every window the run can use is built here: a build takes
    milliseconds, which inside the loop would make a real-time run miss deadlines at each change of rail.
    """

    def __init__(self, cfg: PlantConfig):
        self.cfg = cfg
        self.x0, self.equilibrium_torque_nm = equilibrium(cfg)
        self._x_in = np.zeros(2)
        self._torque_in = np.zeros(1)
        self._t0_in = np.zeros(1)
        self._x_out = np.zeros(2)
        self._mu_out = np.zeros(1)
        self._creep_out = np.zeros(1)
        #: recovering rail segments: the energy each has dissipated (J) and its cleaned fraction rho (plant/rail.py)
        self._cleaned = np.zeros(cfg.cleaning_inputs)
        self.dissipated_j = np.zeros(cfg.cleaning_inputs)
        #: window (None: the whole rail) -> (function, buffer, evaluate); the buffers hold the arrays above
        self._steps: dict = {}
        rail = cfg.rail
        self._rail_events_s = (sorted({x for s in rail.segments[1:] for x in (s.start_s, s.start_s + s.transition_s)})
                               if rail is not None and len(rail.segments) > 1 else [])
        self._window_until_s = -math.inf
        self._eval = None if self._rail_events_s else self._step_for(None)
        for t0_s in self._period_starts_near_events():      # built now, not inside a real-time period
            self._step_for(rail.window_at(t0_s, t0_s + cfg.exchange_period_s, WINDOW_MARGIN_S))
        self.reset()

    def _period_starts_near_events(self) -> list[float]:
        """The start of every period from two before to two after each rail event: the window changes only
        there (``RailSchedule.window_at``), so these periods' windows are every window the run can use."""
        period = self.cfg.exchange_period_s
        steps = {0} | {k for e in self._rail_events_s for k in range(max(int(e / period) - 2, 0), int(e / period) + 3)}
        return [k * period for k in sorted(steps)] if self._rail_events_s else []

    def _step_for(self, window):
        """The evaluate call of the period step of ``window`` (built and bound the first time)."""
        entry = self._steps.get(window)
        if entry is None:
            fn = build_period_step(self.cfg, window)
            args = (self._x_in, self._torque_in, self._t0_in) + ((self._cleaned,) if self.cfg.cleaning_inputs else ())
            entry = self._steps[window] = (fn, *bind_buffer(fn, args, (self._x_out, self._mu_out, self._creep_out)))
        return entry[2]

    def _select_window(self, t0_s: float) -> None:
        """The step function for the period from ``t0_s``, and until when it serves: the next rail event
        (a segment's start or the end of its transition) closer than a period and the margin."""
        margin, period = WINDOW_MARGIN_S, self.cfg.exchange_period_s
        self._eval = self._step_for(self.cfg.rail.window_at(t0_s, t0_s + period, margin))
        ahead = [e for e in self._rail_events_s if e > t0_s - margin]
        self._window_until_s = ahead[0] - period - 2 * margin if ahead else math.inf

    @property
    def cleaned(self) -> tuple[float, ...]:
        """rho of each recovering rail segment (plant/rail.py), in the schedule's order."""
        return tuple(self._cleaned.tolist())

    def reset(self) -> PlantState:
        self.step_index = 0
        self._window_until_s = -math.inf
        self._x_out[:] = self.x0
        self._cleaned[:] = 0.0
        self.dissipated_j[:] = 0.0
        p = self.cfg.params
        v_s = float(creep_speed_kmh(p, self.x0[0], self.x0[1]))
        self._creep_out[0] = v_s
        first = self.cfg.rail.segments[0].curve if self.cfg.rail is not None else self.cfg.normal_curve
        self._mu_out[0] = float(first.mu_at(v_s, self.x0[1]))
        self.state = self._observe(self.equilibrium_torque_nm)
        return self.state

    @property
    def t_s(self) -> float:
        return self.step_index * self.cfg.exchange_period_s

    def step(self, torque_nm: float) -> PlantState:
        self._x_in[:] = self._x_out
        self._torque_in[0] = torque_nm
        t0_s = self._t0_in[0] = self.t_s
        if self._rail_events_s and t0_s >= self._window_until_s:
            self._select_window(t0_s)
        self._eval()
        if not (math.isfinite(self._x_out[0]) and math.isfinite(self._x_out[1])):
            raise FloatingPointError(f"plant diverged at t={self.t_s:.4f} s (torque {torque_nm} N·m)")
        self.step_index += 1
        if self.cfg.cleaning_inputs:
            self._clean()
        self.state = self._observe(torque_nm)
        return self.state

    def _clean(self) -> None:
        """E += mu N w T for the recovering segment the rail is in; rho = 1 - exp(-E / E_clean) (plant/rail.py),
        held over the next period."""
        rail, p = self.cfg.rail, self.cfg.params
        i = rail.index_at(self.t_s)
        if i in rail.recovery:
            j = list(rail.recovery).index(i)
            w_ms = abs(float(self._creep_out[0])) / KMH_PER_MS
            self.dissipated_j[j] += abs(float(self._mu_out[0])) * p.normal_force_n * w_ms * self.cfg.exchange_period_s
            self._cleaned[j] = 1.0 - math.exp(-self.dissipated_j[j] / rail.recovery[i].energy_clean_j)

    def _observe(self, torque_nm: float) -> PlantState:
        t_s = self.t_s
        mu = float(self._mu_out[0])
        return PlantState(t_s, float(self._x_out[0]), float(self._x_out[1]), float(self._creep_out[0]), mu,
                          mu * self.cfg.params.torque_per_mu_nm, float(torque_nm),
                          t_s >= self.cfg.fault_time_s)
