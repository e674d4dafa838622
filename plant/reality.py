"""The reality emulator: effects the nominal wheelset model lacks, each switchable with parameters.

A "real" run is the nominal plant plus one or more of these effects.  Three levels:

* **plant** effects change the physics; ``RealityPlant`` integrates them in CasADi from the same
  curve, creep and Davis expressions as ``plant.model`` (RK4 sub-steps held per exchange period):

  - ``load_transfer``  axle load transfer under traction (Table 1's L, L_b, Z, z).  The faulty axle
    is the leading axle of the leading bogie; its normal force drops with the tractive force of its
    bogie (pitch moment at height z over the wheelbase 2 L_b) and of its car (coupler height Z over
    the bogie distance 2 L, shared by the bogie's two axles):
        N = N0 - (F + F_o) * z / (2 L_b) - (F + 3 F_o) * Z / (4 L),   F = mu N,  F_o = mu_req N0
    solved for N:  N = (N0 - b) / (1 + a mu),  a = z/(2 L_b) + Z/(4 L),  b = F_o (z/(2 L_b) + 3Z/(4 L)).
    The other axles hold their force (mu_req N0): their traction control is not modelled.
  - ``torque_lag``     motor/inverter torque follows the command with a first-order lag tau_s.
  - ``compliance``     drivetrain torsional compliance (stiffness, damping, referred to the motor
    shaft) with gear backlash (half-width, motor-side rad): motor rotor and wheelset become two
    inertias J_m and J_d / (eta R_g^2) joined by the shaft; the motor encoder sees the rotor.
  - ``drivetrain_damping``, ``gear_efficiency``  drivetrain losses: viscous (x motor speed) plus
    Coulomb torque taken off the motor torque; or the torque scaled by a gear efficiency.
  - ``adhesion_lag``   adhesion dynamics: mu relaxes towards the curve's value with time constant
    tau_s (d mu / dt = (mu_curve(v_s) - mu) / tau), so mu lags a changing creep and a rail switch.
    Its other forms: ``creep_relaxation`` (tau = L / v_train: relaxation over a rolled length),
    ``bristle`` (LuGre-type: a bristle state whose relaxation rate is |w| / g(v_s), plus damping) and
    ``adhesion_lag2`` (a second-order lag: mu'' = w^2 (mu_curve - mu) - 2 zeta w mu').
  - ``resistance``     running-resistance mismatch: the Davis polynomial scaled by ``factor``.
  - ``torque_ripple``  (not a diagnosis candidate) sinusoidal ripple on the motor torque.
  - ``power_limit``    (not a diagnosis candidate) the drive's constant-power region: the motor torque
    capped at P_max / omega_m, so above the base speed P_max / T the torque falls as the motor speeds up
        T = min(T_cmd, P_max / omega_m),   P_max = power_kw * 1e3
    (power_kw None: power_ratio x the equilibrium power T0 omega0, binding from power_ratio x omega0).
  - ``torque_map``     (not a diagnosis candidate) the drive's torque gain falling with motor speed,
    linearly about the equilibrium speed omega0 (a torque-speed map of the inverter's control, acting
    from the start as the train speeds up, not from a knee as the power limit):
        T = T_cmd * max(1 - droop * (omega_m / omega0 - 1), 0)
    (omega0_rad_s None: the scenario's equilibrium motor speed; ``droop``: the fraction of torque lost
    per fraction of speed gained).
  - ``wheel_radius``   (not a diagnosis candidate) true wheel radius off the nominal one.
  - ``rail_shape``     (not a diagnosis candidate) the rail's fault curve changed in shape at low creep,
    its peak and tail kept: mu = mu_fault(v_s / k(v_s)), k = 1 + (low_creep_scale - 1) exp(-|v_s| / knee_kmh).

* **sensor** effects (``RealitySensors`` wraps ``plant.SensorModel``): ``sensor_delay`` (delay_ms,
  fractional periods by linear interpolation) and ``sensor_quantisation`` (quanta on top of noise;
  ``motor_noise_after_rad_s``: noise added after the motor encoder's quantiser);
  not diagnosis candidates: ``tachometer_gain`` and ``sensor_stick`` (the motor encoder's reading
  stuck: from reading ``start_s`` / period on, it repeats the last reading it made before, noise
  included, for ``hold_ms``).

* **bus** effects (``can``: delay, jitter, loss of sensor frames) are not physics of the plant: they
  live with the registry of every effect (names, parameters, defaults, which the diagnosis may offer
  as candidates) in ``hil/effects.py``.

This module takes effects as ``{name: {param: value}}`` already checked by that registry.  Each
plant-level effect is its ``Equations`` (``EQUATIONS``, in the order they act): the stages of the
dynamics it changes (torque path, wheel, fault curve, adhesion, normal force, drive, resistance), its
extra states and its consistent start; ``RealityModel`` runs the nominal plant with each effect's
stages in turn, so adding an effect is its record in ``hil/effects.py`` and one ``Equations`` subclass
(``hil.effects.add_effect`` registers it here).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from .model import PlantConfig, PlantState, bind_buffer, creep_speed_kmh, equilibrium, rk4_step
from .params import KMH_PER_MS


#: the bristle model's relaxation rate (1/s) is capped here (time constant >= 0.25 ms, 2.5 RK4
#: sub-steps, a quarter period): the cap slows only transients faster than a sample, never the steady state
BRISTLE_MAX_RATE_1_S = 4000.0
#: the sensor-level effects ``RealitySensors`` applies
SENSOR_EFFECTS = ("sensor_delay", "sensor_lowpass", "motor_delay", "tachometer_gain", "sensor_stick",
                  "sensor_quantisation")


def load_transfer_coefficients(cfg: PlantConfig, L, L_b, Z, z):
    """(a, b_n) of N = (N0 - b) / (1 + a mu) for the leading axle of the leading bogie."""
    f_o = cfg.mu_required * cfg.params.normal_force_n
    a = z / (2 * L_b) + Z / (4 * L)
    b = f_o * (z / (2 * L_b) + 3 * Z / (4 * L))
    return a, b


# -- the equations of each plant-level effect ---------------------------------------------------------
class Terms:
    """One evaluation of the dynamics (``RealityModel.rhs``): the quantities the effects' equations read
    and change, stage after stage.  Starts as the nominal plant: torque = the command, the wheel turns
    with the motor on the nominal radius; ``mu``, ``normal`` and the motor's acceleration are the
    nominal ones unless an effect's stage sets them."""

    def __init__(self, model: "RealityModel", x, torque_cmd, t):
        self.cfg, self.p, self.x, self.t = model.cfg, model.cfg.params, x, t
        self._names = model.state_names
        self.dx = [None] * model.nx
        self.torque_cmd = self.torque = torque_cmd
        self.omega_m, self.v_t = x[0], x[1]
        self.omega_wheel = self.omega_m
        self.radius = self.p.wheel_radius_m
        self.v_s = self.fault = self.mu_curve = self.mu = self.normal = None
        self.force = self.load_torque = self.resistance = None

    def state(self, name: str):
        return self.x[self._names.index(name)]

    def set_rate(self, name: str, expr) -> None:
        self.dx[self._names.index(name)] = expr


class Start:
    """What ``RealityModel.initial_state`` gives each effect's ``initial``: the state vector being
    filled (``x``, ``set``), mu on the curve at the start (``mu0``), the torque, the configuration."""

    def __init__(self, model: "RealityModel", x, mu0: float, torque0: float, x0_nominal):
        self.cfg, self.p, self.x, self.mu0, self.torque0, self.x0_nominal = \
            model.cfg, model.cfg.params, x, mu0, torque0, x0_nominal
        self._names = model.state_names

    def set(self, name: str, value: float) -> None:
        self.x[self._names.index(name)] = value


class Equations:
    """A plant-level effect's equations: the stages of ``RealityModel.rhs`` it changes (each reads and
    sets ``Terms``; ``e`` is the effect's parameters, numbers or CasADi symbols), its extra states
    (``states``, placed in the state vector by ``state_rank``), its consistent initial state and its
    scenario-dependent defaults.  Stages, in order: ``torque`` (the torque path, effects in registry
    order), ``wheel`` (wheel speed, radius), ``curve`` (the fault curve), ``adhesion`` (mu from the
    curve's value), ``normal`` (the axle's normal force), ``drive`` (the motor's and wheel's
    accelerations), ``resistance`` (the running resistance).  ``claims``: a quantity only one effect
    of a model may set ("mu", "normal"; "" for none)."""

    states: tuple = ()
    state_rank: int = 99
    claims: str = ""

    def defaults(self, q: dict, cfg: PlantConfig) -> None:
        """Fill the scenario-dependent parameters (None) of ``q`` in place."""

    def torque(self, e, v: Terms) -> None: ...
    def wheel(self, e, v: Terms) -> None: ...
    def curve(self, e, v: Terms) -> None: ...
    def adhesion(self, e, v: Terms) -> None: ...
    def normal(self, e, v: Terms) -> None: ...
    def drive(self, e, v: Terms) -> None: ...
    def resistance(self, e, v: Terms) -> None: ...

    def initial_mu(self, e, mu0: float, curve, v_s: float, v_t: float) -> float:
        """mu on the (fault) curve at the start, as this effect changes it."""
        return mu0

    def initial(self, e, s: Start) -> None:
        """Its extra states at the start, consistent with the nominal state (``Start``)."""


class TorqueLag(Equations):
    """Motor/inverter torque follows the command with a first-order lag: dT/dt = (T_cmd - T) / tau."""
    states, state_rank = ("torque_actual",), 2

    def torque(self, e, v):
        actual = v.state("torque_actual")
        v.set_rate("torque_actual", (v.torque_cmd - actual) / e["tau_s"])
        v.torque = actual

    def initial(self, e, s):
        s.set("torque_actual", s.torque0)


class PowerLimit(Equations):
    """T = min(T, P_max / omega_m), P_max = power_kw * 1e3."""

    def defaults(self, q, cfg):
        if q.get("power_kw") is None:
            x0, torque0 = equilibrium(cfg)
            q["power_kw"] = float(q.get("power_ratio", 1.0) * torque0 * x0[0] * 1e-3)

    def torque(self, e, v):
        v.torque = ca.fmin(v.torque, e["power_kw"] * 1e3 / ca.fmax(v.omega_m, 1.0))


class TorqueMap(Equations):
    """T = T * max(1 - droop (omega_m / omega0 - 1), 0)."""

    def defaults(self, q, cfg):
        if q.get("omega0_rad_s") is None:
            q["omega0_rad_s"] = float(equilibrium(cfg)[0][0])

    def torque(self, e, v):
        v.torque = v.torque * ca.fmax(1 - e["droop"] * (v.omega_m / e["omega0_rad_s"] - 1), 0)


class TorqueRipple(Equations):
    """T = T (1 + a sin(2 pi f t + phase))."""

    def torque(self, e, v):
        v.torque = v.torque * (1 + e["amplitude"] * ca.sin(2 * math.pi * e["frequency_hz"] * v.t + e["phase_rad"]))


class DrivetrainDamping(Equations):
    """T = T - c omega_m - T_c tanh(omega_m / 0.1)."""

    def torque(self, e, v):
        v.torque = v.torque - e["viscous_nm_s_rad"] * v.omega_m - e["coulomb_nm"] * ca.tanh(v.omega_m / 0.1)


class GearEfficiency(Equations):
    """T = efficiency x T."""

    def torque(self, e, v):
        v.torque = v.torque * e["efficiency"]


class Compliance(Equations):
    """Motor rotor and wheelset as two inertias J_m and J_d / (eta R_g^2) joined by a shaft of stiffness
    k and damping 2 zeta sqrt(k J_red), with backlash beta (half-width): the shaft torque is
    k (twist - sgn(twist) beta) + c (omega_m - omega_w) in contact (|twist| > beta), else 0."""
    states, state_rank, claims = ("omega_w", "twist"), 1, "drive"

    def wheel(self, e, v):
        v.omega_wheel = v.state("omega_w")

    def drive(self, e, v):
        p = v.p
        j_w = p.wheelset_inertia_kgm2 / (p.efficiency * p.gear_ratio ** 2)
        k, beta = e["stiffness_nm_rad"], e["backlash_rad"]
        j_red = p.motor_inertia_kgm2 * j_w / (p.motor_inertia_kgm2 + j_w)
        damping = 2 * e["damping_ratio"] * ca.sqrt(k * j_red)
        twist = v.state("twist")
        rel = v.omega_m - v.omega_wheel
        contact = ca.fabs(twist) > beta
        shaft = ca.if_else(contact, k * (twist - ca.sign(twist) * beta) + damping * rel, 0)
        v.dx[0] = (v.torque - shaft) / p.motor_inertia_kgm2
        v.set_rate("omega_w", (shaft - v.load_torque) / j_w)
        v.set_rate("twist", rel)

    def initial(self, e, s):
        p = s.p
        s.set("omega_w", s.x0_nominal[0])
        # shaft torque that gives the rotor the same acceleration as the rigid model's
        accel = (s.torque0 - s.mu0 * p.torque_per_mu_nm) / p.equivalent_inertia_kgm2
        shaft = s.torque0 - p.motor_inertia_kgm2 * accel
        s.set("twist", shaft / float(e["stiffness_nm_rad"]) + math.copysign(float(e["backlash_rad"]), shaft))


class WheelRadius(Equations):
    """r = r_nominal (1 + error_percent / 100)."""

    def wheel(self, e, v):
        v.radius = v.p.wheel_radius_m * (1 + e["error_percent"] / 100)


class RailCurve(Equations):
    """mu_fault = peak_mu_scale * mu_fault(v_s / creep_scale)."""

    def curve(self, e, v):
        v.fault = e["peak_mu_scale"] * v.cfg.fault_curve.mu_casadi(v.v_s / e["creep_scale"], v.v_t)

    def initial_mu(self, e, mu0, curve, v_s, v_t):
        return float(e["peak_mu_scale"] * curve.mu_at(v_s / float(e["creep_scale"]), v_t))


class RailShape(Equations):
    """The rail's fault curve changed in shape at low creep, its peak and tail kept:
    mu_fault = mu_fault(v_s / k(v_s)), k(v_s) = 1 + (low_creep_scale - 1) exp(-|v_s| / knee_kmh): the
    curve stretched (k > 1) or squeezed (k < 1) in creep near zero, the stretch fading over
    ``knee_kmh``.  v_s / k(v_s) rises with v_s for every low_creep_scale > 0 (its slope is
    (1 + (k0 - 1) e^-x (1 + x)) / k^2, x = |v_s| / knee), so the curve keeps its order.  No scaling of
    the whole curve (the rail nuisance, ``RailCurve``) reproduces it (issue 51)."""

    @staticmethod
    def _k(e, v_s, exp, fabs):
        return 1 + (e["low_creep_scale"] - 1) * exp(-fabs(v_s) / e["knee_kmh"])

    def curve(self, e, v):
        v.fault = v.cfg.fault_curve.mu_casadi(v.v_s / self._k(e, v.v_s, ca.exp, ca.fabs), v.v_t)

    def initial_mu(self, e, mu0, curve, v_s, v_t):
        return float(curve.mu_at(v_s / float(self._k(e, v_s, math.exp, abs)), v_t))


class AdhesionLag(Equations):
    """d mu / dt = (mu_curve(v_s) - mu) / tau."""
    states, state_rank, claims = ("mu_state",), 3, "mu"

    def adhesion(self, e, v):
        v.mu = v.state("mu_state")
        v.set_rate("mu_state", (v.mu_curve - v.mu) / e["tau_s"])

    def initial(self, e, s):
        s.set("mu_state", s.mu0)


class CreepRelaxation(Equations):
    """d mu / dt = (mu_curve(v_s) - mu) max(|v_t|, 0.1) / L: relaxation over a rolled length L."""
    states, state_rank, claims = ("mu_state",), 3, "mu"

    def adhesion(self, e, v):
        v.mu = v.state("mu_state")
        rate = ca.fmax(ca.fabs(v.v_t), 0.1) / e["relaxation_length_m"]
        v.set_rate("mu_state", (v.mu_curve - v.mu) * rate)

    def initial(self, e, s):
        s.set("mu_state", s.mu0)


class SecondOrderAdhesion(Equations):
    """Adhesion dynamics as a second-order contact lag: mu'' = w^2 (mu_curve(v_s) - mu) - 2 zeta w mu',
    w = 2 pi natural_hz (a contact patch whose stress builds up through a mass-spring-like lag: issue 51
    found this form answered "none" by the first-order forms)."""
    states, state_rank, claims = ("mu_state", "mu_rate"), 3, "mu"

    def adhesion(self, e, v):
        v.mu = v.state("mu_state")
        rate = v.state("mu_rate")
        w = 2 * math.pi * e["natural_hz"]
        v.set_rate("mu_state", rate)
        v.set_rate("mu_rate", w * w * (v.mu_curve - v.mu) - 2 * e["damping_ratio"] * w * rate)

    def initial(self, e, s):
        s.set("mu_state", s.mu0)


class Bristle(Equations):
    """LuGre-type bristle: z' = w - |w| z / g = (|w| / g) (g sgn(w) - z), g = mu_curve(v_s) / sigma0,
    mu = sigma0 z + sigma1 z' (w slip velocity, m/s).  Written as a relaxation towards the steady
    deflection g sgn(w) so that capping its rate (``BRISTLE_MAX_RATE_1_S``) keeps the steady state
    mu = mu_curve."""
    states, state_rank, claims = ("bristle_z",), 4, "mu"

    def adhesion(self, e, v):
        s0, s1 = e["stiffness_per_m"], e["damping_s_per_m"]
        w = v.v_s / KMH_PER_MS
        g = ca.fmax(ca.fabs(v.mu_curve), 1e-6) / s0
        z = v.state("bristle_z")
        rate = ca.fmin(ca.fabs(w) / g, BRISTLE_MAX_RATE_1_S)
        zdot = rate * (g * ca.sign(w) - z)
        v.set_rate("bristle_z", zdot)
        v.mu = s0 * z + s1 * zdot

    def initial(self, e, s):
        s.set("bristle_z", s.mu0 / float(e["stiffness_per_m"]))


_VEHICLE_GEOMETRY = ("half_bogie_distance_m", "half_wheelbase_m", "coupler_height_m", "bogie_height_m")


class LoadTransfer(Equations):
    """N = (N0 - b) / (1 + a mu) (``load_transfer_coefficients``; the geometry defaults to the
    scenario's vehicle)."""
    claims = "normal"

    def defaults(self, q, cfg):
        for k in _VEHICLE_GEOMETRY:
            if q.get(k) is None:
                q[k] = float(getattr(cfg.params, k))

    def coefficients(self, e, cfg):
        return load_transfer_coefficients(cfg, e["half_bogie_distance_m"], e["half_wheelbase_m"],
                                          e["coupler_height_m"], e["bogie_height_m"])

    def normal(self, e, v):
        a, b = self.coefficients(e, v.cfg)
        v.normal = (v.p.normal_force_n - b) / (1 + a * v.mu)


class LoadTransferPitch(LoadTransfer):
    """The static transfer through a pitch mode: N = N0 + d, d'' = w^2 (d_static - d) - 2 zeta w d',
    d_static = (N0 - b) / (1 + a mu) - N0, w = 2 pi pitch_hz."""
    states, state_rank = ("normal_dev", "normal_dev_rate"), 5

    def normal(self, e, v):
        a, b = self.coefficients(e, v.cfg)
        n0 = v.p.normal_force_n
        d, dd = v.state("normal_dev"), v.state("normal_dev_rate")
        w = 2 * math.pi * e["pitch_hz"]
        d_static = (n0 - b) / (1 + a * v.mu) - n0
        v.set_rate("normal_dev", dd)
        v.set_rate("normal_dev_rate", w * w * (d_static - d) - 2 * e["pitch_damping"] * w * dd)
        v.normal = n0 + d

    def initial(self, e, s):
        a, b = self.coefficients(e, s.cfg)
        n0 = s.p.normal_force_n
        s.set("normal_dev", float((n0 - b) / (1 + a * s.mu0) - n0))


class Resistance(Equations):
    """R = factor x the Davis polynomial."""

    def resistance(self, e, v):
        v.resistance = v.resistance * e["factor"]


#: every plant-level effect's equations, in the order they act on the torque path (and so on every
#: stage); ``add_equations`` appends one
EQUATIONS: dict[str, Equations] = {
    "torque_lag": TorqueLag(), "power_limit": PowerLimit(), "torque_map": TorqueMap(),
    "torque_ripple": TorqueRipple(), "drivetrain_damping": DrivetrainDamping(),
    "gear_efficiency": GearEfficiency(), "compliance": Compliance(), "wheel_radius": WheelRadius(),
    "rail_curve": RailCurve(), "rail_shape": RailShape(), "adhesion_lag": AdhesionLag(), "creep_relaxation": CreepRelaxation(),
    "bristle": Bristle(), "adhesion_lag2": SecondOrderAdhesion(), "load_transfer": LoadTransfer(), "load_transfer_pitch": LoadTransferPitch(),
    "resistance": Resistance(),
}


def add_equations(name: str, equations: Equations) -> None:
    """Register a new plant-level effect's equations (``hil.effects.add_effect`` calls this with the
    effect's record); it acts after every effect registered before it."""
    if name in EQUATIONS and EQUATIONS[name] is not equations:
        raise ValueError(f"plant effect {name!r} already has equations")
    EQUATIONS[name] = equations


def plant_order() -> tuple[str, ...]:
    """The plant-level effects this module integrates, in the order they act."""
    return tuple(EQUATIONS)


#: the plant-level effects built in, in the order they act (``plant_order()`` includes any added)
PLANT_ORDER = plant_order()


def fill_defaults(effects: dict, cfg: PlantConfig) -> dict:
    """Effects with scenario-dependent defaults (None) replaced by the scenario's values."""
    out = {}
    for name, params in effects.items():
        q = dict(params)
        if name in EQUATIONS:
            EQUATIONS[name].defaults(q, cfg)
        out[name] = q
    return out


def plant_effects(effects: dict) -> dict:
    return {k: v for k, v in effects.items() if k in EQUATIONS}


class RealityModel:
    """Continuous-time dynamics of the nominal plant plus the given plant-level effects.

    ``effects`` maps effect name -> {param: value}; a value may be a number or a CasADi symbol (the
    diagnosis fits them).  States: omega_m, v_t, then each effect's own (``Equations.states``, by
    ``state_rank``: [omega_w, twist] with compliance, [T_a] with torque lag, [mu_state] with adhesion
    lag or creep relaxation, [z] with the bristle, [d, d'] with the pitch mode).  The effects act in
    ``EQUATIONS`` order; two that set the same quantity (two adhesion forms, two load transfers) are
    refused.
    """

    def __init__(self, cfg: PlantConfig, effects: dict):
        self.cfg = cfg
        self.effects = plant_effects(effects)
        self._eqs = [(n, EQUATIONS[n]) for n in EQUATIONS if n in self.effects]
        claimed: dict[str, str] = {}
        for n, eq in self._eqs:
            if eq.claims and eq.claims in claimed:
                raise ValueError(f"plant effects {claimed[eq.claims]!r} and {n!r} both set {eq.claims}: "
                                 "a model takes one of them")
            if eq.claims:
                claimed[eq.claims] = n
        names = ["omega_m", "v_t"]
        for _, eq in sorted(self._eqs, key=lambda ne: ne[1].state_rank):
            names += [s for s in eq.states if s not in names]
        self.state_names = names
        self.nx = len(names)

    def rhs(self, x, torque_cmd, t):
        """(dx, mu, v_s_kmh, normal_force_n) as CasADi expressions: the nominal plant (plant.model) with
        each effect's stages (``Equations``) applied in turn."""
        cfg, p = self.cfg, self.cfg.params
        v = Terms(self, x, torque_cmd, t)
        eqs = [(eq, self.effects[n]) for n, eq in self._eqs]
        for eq, e in eqs:
            eq.torque(e, v)
        for eq, e in eqs:
            eq.wheel(e, v)
        v.v_s = KMH_PER_MS * (v.omega_wheel / p.gear_ratio * v.radius - v.v_t)
        v.fault = cfg.fault_curve.mu_casadi(v.v_s, v.v_t)
        for eq, e in eqs:
            eq.curve(e, v)
        v.mu_curve = ca.if_else(t >= cfg.fault_time_s, v.fault, cfg.normal_curve.mu_casadi(v.v_s, v.v_t))
        for eq, e in eqs:
            eq.adhesion(e, v)
        if v.mu is None:
            v.mu = v.mu_curve
        for eq, e in eqs:
            eq.normal(e, v)
        if v.normal is None:
            v.normal = p.normal_force_n
        v.force = v.mu * v.normal
        v.load_torque = v.force * v.radius / (p.efficiency * p.gear_ratio)
        for eq, e in eqs:
            eq.drive(e, v)
        if v.dx[0] is None:
            v.dx[0] = (v.torque - v.load_torque) / p.equivalent_inertia_kgm2
        v.resistance = p.running_resistance_n(v.v_t)
        for eq, e in eqs:
            eq.resistance(e, v)
        other = (p.driven_axles - 1) * cfg.mu_required * p.normal_force_n
        v.dx[1] = (v.force + other - v.resistance) / p.train_mass_kg
        return ca.vertcat(*v.dx), v.mu, v.v_s, v.normal

    def initial_state(self, x0_nominal, torque0: float, t0: float = 0.0) -> np.ndarray:
        """Extra states consistent with the nominal (omega_m, v_t) and torque: no twist transient,
        torque at the command, mu on the curve."""
        cfg = self.cfg
        p = cfg.params
        x = np.zeros(self.nx)
        x[:2] = x0_nominal[:2]
        v_s = float(creep_speed_kmh(p, x0_nominal[0], x0_nominal[1]))
        curve = cfg.fault_curve if t0 >= cfg.fault_time_s else cfg.normal_curve
        mu0 = float(curve.mu_at(v_s, x0_nominal[1]))
        if t0 >= cfg.fault_time_s:
            for n, eq in self._eqs:
                mu0 = eq.initial_mu(self.effects[n], mu0, curve, v_s, x0_nominal[1])
        start = Start(self, x, mu0, torque0, x0_nominal)
        for n, eq in self._eqs:
            eq.initial(self.effects[n], start)
        return x

    def period_step(self, param_syms=None) -> ca.Function:
        """F(x0, T_cmd, t0[, p]) -> (x, mu, v_s_kmh, N) at t0 + exchange period."""
        cfg = self.cfg
        x0 = ca.SX.sym("x", self.nx)
        u = ca.SX.sym("torque_nm")
        t0 = ca.SX.sym("t0_s")
        h = cfg.integration_step_s
        x = x0
        f = lambda x_, u_, t_: self.rhs(x_, u_, t_)[0]  # noqa: E731
        for i in range(cfg.substeps):
            x = rk4_step(f, x, u, t0 + i * h, h)
        _, mu, v_s, normal = self.rhs(x, u, t0 + cfg.substeps * h)
        ins = [x0, u, t0] + ([param_syms] if param_syms is not None else [])
        return ca.Function("reality_period_step", ins, [x, mu, v_s, normal])


class RealityPlant:
    """WheelsetPlant's interface (``step(torque_nm) -> PlantState``, ``reset``, ``state``, ``t_s``,
    ``step_index``, ``x0``, ``equilibrium_torque_nm``) for the nominal plant plus plant-level effects.

    Starts from the nominal equilibrium (what the scenario and the TCU assume), so an effect that
    moves the equilibrium shows as a transient from t = 0, as on a real vehicle.
    """

    def __init__(self, cfg: PlantConfig, effects: dict):
        self.cfg = cfg
        self.effects = fill_defaults(plant_effects(effects), cfg)
        self.model = RealityModel(cfg, self.effects)
        self._step_fn = self.model.period_step()
        x0_nom, self.equilibrium_torque_nm = equilibrium(cfg)
        self.x0 = self.model.initial_state(x0_nom, self.equilibrium_torque_nm)
        n = self.model.nx
        self._x_in, self._u_in, self._t_in = np.zeros(n), np.zeros(1), np.zeros(1)
        self._x_out, self._mu_out, self._vs_out, self._n_out = np.zeros(n), np.zeros(1), np.zeros(1), np.zeros(1)
        self._buffer, self._eval = bind_buffer(self._step_fn, (self._x_in, self._u_in, self._t_in),
                                               (self._x_out, self._mu_out, self._vs_out, self._n_out))
        self.reset()

    def reset(self) -> PlantState:
        self.step_index = 0
        self._x_out[:] = self.x0
        self._u_in[0] = self.equilibrium_torque_nm
        self._t_in[0] = 0.0
        self._x_in[:] = self.x0
        # outputs at t = 0 from a zero-length evaluation of the dynamics
        xs = ca.SX.sym("x", self.model.nx)
        _, mu, v_s, normal = self.model.rhs(xs, self.equilibrium_torque_nm, 0.0)
        out = ca.Function("out0", [xs], [mu, v_s, normal])(self.x0)
        self._mu_out[0], self._vs_out[0], self._n_out[0] = (float(v) for v in out)
        self.state = self._observe(self.equilibrium_torque_nm)
        return self.state

    @property
    def t_s(self) -> float:
        return self.step_index * self.cfg.exchange_period_s

    def step(self, torque_nm: float) -> PlantState:
        self._x_in[:] = self._x_out
        self._u_in[0] = torque_nm
        self._t_in[0] = self.t_s
        self._eval()
        if not np.all(np.isfinite(self._x_out)):
            raise FloatingPointError(f"reality plant diverged at t={self.t_s:.4f} s (torque {torque_nm} N·m)")
        self.step_index += 1
        self.state = self._observe(torque_nm)
        return self.state

    def _observe(self, torque_nm: float) -> PlantState:
        t_s = self.t_s
        p = self.cfg.params
        mu = float(self._mu_out[0])
        load = mu * float(self._n_out[0]) * p.wheel_radius_m / (p.efficiency * p.gear_ratio)
        return PlantState(t_s, float(self._x_out[0]), float(self._x_out[1]), float(self._vs_out[0]), mu, load,
                          float(torque_nm), t_s >= self.cfg.fault_time_s)


# -- sensor-level ---------------------------------------------------------------------------------------
class RealitySensors:
    """Wraps a ``SensorModel`` (``measure(omega, v)``, called once per exchange period): delays the true
    speeds by ``delay_ms`` (linear interpolation between periods), then the inner model adds its noise
    and quantisation, then the reality quanta apply."""

    def __init__(self, inner, effects: dict, period_s: float):
        self.inner = inner
        self.cfg = inner.cfg
        d = effects.get("sensor_delay", {}).get("delay_ms", 0.0)
        self.delay_periods = d * 1e-3 / period_s
        self.motor_delay_periods = effects.get("motor_delay", {}).get("delay_ms", 0.0) * 1e-3 / period_s
        tau = effects.get("sensor_lowpass", {}).get("tau_ms", 0.0) * 1e-3
        self.lowpass = math.exp(-period_s / tau) if tau > 0 else 0.0   # y += (1 - a) (x - y) per period
        self._lp = None
        self.motor_gain = 1.0 + effects.get("tachometer_gain", {}).get("error_percent", 0.0) / 100.0
        q = effects.get("sensor_quantisation", {})
        self.q_motor = q.get("motor_quantum_rad_s", 0.0)
        self.q_train = q.get("train_quantum_ms", 0.0)
        # noise after the motor encoder's quantiser (its electronics after the counter): its own stream,
        # seeded from the sensor model's, drawn only when asked for (other runs keep their numbers)
        self.noise_after = q.get("motor_noise_after_rad_s", 0.0)
        self._rng_after = np.random.default_rng(inner._rng.integers(1 << 62)) if self.noise_after > 0 else None
        st = effects.get("sensor_stick")
        self.stick = (round(st["start_s"] / period_s), round((st["start_s"] + st["hold_ms"] * 1e-3) / period_s)) \
            if st else None
        self._stuck = None
        self._hist: list[tuple[float, float]] = []

    def measure(self, motor_speed_rad_s: float, train_speed_ms: float) -> tuple[float, float]:
        self._hist.append((motor_speed_rad_s, train_speed_ms))
        if self.lowpass > 0:
            if self._lp is None:
                self._lp = (motor_speed_rad_s, train_speed_ms)
            a = self.lowpass
            self._lp = tuple(a * y + (1 - a) * x for y, x in zip(self._lp, (motor_speed_rad_s, train_speed_ms)))
            motor_speed_rad_s, train_speed_ms = self._lp
        if self.delay_periods > 0 or self.motor_delay_periods > 0:
            k = len(self._hist) - 1

            def late(periods, j):
                pos = max(k - periods, 0.0)
                i = int(math.floor(pos))
                frac = pos - i
                return self._hist[i][j] + frac * (self._hist[min(i + 1, k)][j] - self._hist[i][j])

            if self.delay_periods > 0:
                motor_speed_rad_s, train_speed_ms = late(self.delay_periods, 0), late(self.delay_periods, 1)
            if self.motor_delay_periods > 0:
                motor_speed_rad_s = late(self.motor_delay_periods, 0)
            keep = int(max(self.delay_periods, self.motor_delay_periods)) + 3
            if len(self._hist) > 4 * keep + 100:   # bounded memory on long runs
                del self._hist[:len(self._hist) - keep - 1]
        omega, v = self.inner.measure(motor_speed_rad_s * self.motor_gain, train_speed_ms)
        if self.q_motor > 0:
            omega = float(np.round(omega / self.q_motor) * self.q_motor)
        if self._rng_after is not None:
            omega += self.noise_after * float(self._rng_after.standard_normal())
        if self.q_train > 0:
            v = float(np.round(v / self.q_train) * self.q_train)
        if self.stick is not None:
            k = len(self._hist) - 1                   # this reading's period
            if k < self.stick[0]:
                self._stuck = omega                   # the last reading before the encoder sticks
            elif k < self.stick[1] and self._stuck is not None:
                omega = self._stuck
        return omega, v
