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
    Its other forms: ``creep_relaxation`` (tau = L / v_train: relaxation over a rolled length) and
    ``bristle`` (LuGre-type: a bristle state whose relaxation rate is |w| / g(v_s), plus damping).
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

* **sensor** effects (``RealitySensors`` wraps ``plant.SensorModel``): ``sensor_delay`` (delay_ms,
  fractional periods by linear interpolation) and ``sensor_quantisation`` (quanta on top of noise);
  not diagnosis candidates: ``tachometer_gain`` and ``sensor_stick`` (the motor encoder's reading
  stuck: from reading ``start_s`` / period on, it repeats the last reading it made before, noise
  included, for ``hold_ms``).

* **bus** effects (``can``: delay, jitter, loss of sensor frames) are not physics of the plant: they
  live with the registry of every effect (names, parameters, defaults, which the diagnosis may offer
  as candidates) in ``hil/effects.py``.

This module takes effects as ``{name: {param: value}}`` already checked by that registry.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from .model import PlantConfig, PlantState, bind_buffer, creep_speed_kmh, equilibrium, rk4_step
from .params import KMH_PER_MS


#: the plant-level effects this module integrates, in the order they act on the torque path
PLANT_ORDER = ("torque_lag", "power_limit", "torque_map", "torque_ripple", "drivetrain_damping", "gear_efficiency",
               "compliance", "wheel_radius", "rail_curve",
               "adhesion_lag", "creep_relaxation", "bristle", "load_transfer", "load_transfer_pitch", "resistance")
#: the bristle model's relaxation rate (1/s) is capped here (time constant >= 0.25 ms, 2.5 RK4
#: sub-steps, a quarter period): the cap slows only transients faster than a sample, never the steady state
BRISTLE_MAX_RATE_1_S = 4000.0
#: the sensor-level effects ``RealitySensors`` applies
SENSOR_EFFECTS = ("sensor_delay", "sensor_lowpass", "motor_delay", "tachometer_gain", "sensor_stick",
                  "sensor_quantisation")


def fill_defaults(effects: dict, cfg: PlantConfig) -> dict:
    """Effects with scenario-dependent defaults (None) replaced by the scenario's values."""
    p = cfg.params
    out = {}
    for name, params in effects.items():
        q = dict(params)
        if name in ("load_transfer", "load_transfer_pitch"):
            for k in ("half_bogie_distance_m", "half_wheelbase_m", "coupler_height_m", "bogie_height_m"):
                if q.get(k) is None:
                    q[k] = float(getattr(p, k))
        if name == "power_limit" and q.get("power_kw") is None:
            x0, torque0 = equilibrium(cfg)
            q["power_kw"] = float(q.get("power_ratio", 1.0) * torque0 * x0[0] * 1e-3)
        if name == "torque_map" and q.get("omega0_rad_s") is None:
            q["omega0_rad_s"] = float(equilibrium(cfg)[0][0])
        out[name] = q
    return out


def plant_effects(effects: dict) -> dict:
    return {k: v for k, v in effects.items() if k in PLANT_ORDER}


# -- plant-level physics ----------------------------------------------------------------------------
def load_transfer_coefficients(cfg: PlantConfig, L, L_b, Z, z):
    """(a, b_n) of N = (N0 - b) / (1 + a mu) for the leading axle of the leading bogie."""
    f_o = cfg.mu_required * cfg.params.normal_force_n
    a = z / (2 * L_b) + Z / (4 * L)
    b = f_o * (z / (2 * L_b) + 3 * Z / (4 * L))
    return a, b


class RealityModel:
    """Continuous-time dynamics of the nominal plant plus the given plant-level effects.

    ``effects`` maps effect name -> {param: value}; a value may be a number or a CasADi symbol (the
    diagnosis fits them).  States: omega_m, v_t, then [omega_w (wheel, motor side), twist] with
    compliance, [T_a] with torque lag, [mu_s] with adhesion lag.
    """

    def __init__(self, cfg: PlantConfig, effects: dict):
        self.cfg = cfg
        self.effects = plant_effects(effects)
        names = ["omega_m", "v_t"]
        if "compliance" in self.effects:
            names += ["omega_w", "twist"]
        if "torque_lag" in self.effects:
            names += ["torque_actual"]
        if "adhesion_lag" in self.effects or "creep_relaxation" in self.effects:
            names += ["mu_state"]
        if "bristle" in self.effects:
            names += ["bristle_z"]
        if "load_transfer_pitch" in self.effects:
            names += ["normal_dev", "normal_dev_rate"]
        self.state_names = names
        self.nx = len(names)

    def _i(self, name):
        return self.state_names.index(name)

    def rhs(self, x, torque_cmd, t):
        """(dx, mu, v_s_kmh, normal_force_n) as CasADi expressions."""
        cfg, e = self.cfg, self.effects
        p = cfg.params
        j_w = p.wheelset_inertia_kgm2 / (p.efficiency * p.gear_ratio ** 2)
        omega_m, v_t = x[0], x[1]
        dx = [None] * self.nx
        torque = x[self._i("torque_actual")] if "torque_lag" in e else torque_cmd
        if "torque_lag" in e:
            dx[self._i("torque_actual")] = (torque_cmd - torque) / e["torque_lag"]["tau_s"]
        if "power_limit" in e:
            torque = ca.fmin(torque, e["power_limit"]["power_kw"] * 1e3 / ca.fmax(omega_m, 1.0))
        if "torque_map" in e:
            tm = e["torque_map"]
            torque = torque * ca.fmax(1 - tm["droop"] * (omega_m / tm["omega0_rad_s"] - 1), 0)
        if "torque_ripple" in e:
            r = e["torque_ripple"]
            torque = torque * (1 + r["amplitude"] * ca.sin(2 * math.pi * r["frequency_hz"] * t + r["phase_rad"]))
        if "drivetrain_damping" in e:
            dd = e["drivetrain_damping"]
            torque = torque - dd["viscous_nm_s_rad"] * omega_m - dd["coulomb_nm"] * ca.tanh(omega_m / 0.1)
        if "gear_efficiency" in e:
            torque = torque * e["gear_efficiency"]["efficiency"]
        omega_wheel = x[self._i("omega_w")] if "compliance" in e else omega_m
        radius = p.wheel_radius_m * (1 + e["wheel_radius"]["error_percent"] / 100) if "wheel_radius" in e \
            else p.wheel_radius_m
        v_s = KMH_PER_MS * (omega_wheel / p.gear_ratio * radius - v_t)
        fault = cfg.fault_curve.mu_casadi(v_s, v_t)
        if "rail_curve" in e:
            rc = e["rail_curve"]
            fault = rc["peak_mu_scale"] * cfg.fault_curve.mu_casadi(v_s / rc["creep_scale"], v_t)
        mu_curve = ca.if_else(t >= cfg.fault_time_s, fault, cfg.normal_curve.mu_casadi(v_s, v_t))
        if "adhesion_lag" in e:
            mu = x[self._i("mu_state")]
            dx[self._i("mu_state")] = (mu_curve - mu) / e["adhesion_lag"]["tau_s"]
        elif "creep_relaxation" in e:
            mu = x[self._i("mu_state")]
            rate = ca.fmax(ca.fabs(v_t), 0.1) / e["creep_relaxation"]["relaxation_length_m"]
            dx[self._i("mu_state")] = (mu_curve - mu) * rate
        elif "bristle" in e:
            # LuGre-type bristle: z' = w - |w| z / g = (|w| / g) (g sgn(w) - z), g = mu_curve(v_s) / sigma0,
            # mu = sigma0 z + sigma1 z' (w slip velocity, m/s).  Written as a relaxation towards the steady
            # deflection g sgn(w) so that capping its rate (stiffness) keeps the steady state mu = mu_curve.
            br = e["bristle"]
            s0, s1 = br["stiffness_per_m"], br["damping_s_per_m"]
            w = v_s / KMH_PER_MS
            g = ca.fmax(ca.fabs(mu_curve), 1e-6) / s0
            z = x[self._i("bristle_z")]
            rate = ca.fmin(ca.fabs(w) / g, BRISTLE_MAX_RATE_1_S)
            zdot = rate * (g * ca.sign(w) - z)
            dx[self._i("bristle_z")] = zdot
            mu = s0 * z + s1 * zdot
        else:
            mu = mu_curve
        n0 = p.normal_force_n
        if "load_transfer" in e:
            lt = e["load_transfer"]
            a, b = load_transfer_coefficients(cfg, lt["half_bogie_distance_m"], lt["half_wheelbase_m"],
                                              lt["coupler_height_m"], lt["bogie_height_m"])
            normal = (n0 - b) / (1 + a * mu)
        elif "load_transfer_pitch" in e:
            # the static transfer through a pitch mode: N = N0 + d, d'' = w^2 (d_static - d) - 2 zeta w d'
            lt = e["load_transfer_pitch"]
            a, b = load_transfer_coefficients(cfg, lt["half_bogie_distance_m"], lt["half_wheelbase_m"],
                                              lt["coupler_height_m"], lt["bogie_height_m"])
            d, dd = x[self._i("normal_dev")], x[self._i("normal_dev_rate")]
            w = 2 * math.pi * lt["pitch_hz"]
            d_static = (n0 - b) / (1 + a * mu) - n0
            dx[self._i("normal_dev")] = dd
            dx[self._i("normal_dev_rate")] = w * w * (d_static - d) - 2 * lt["pitch_damping"] * w * dd
            normal = n0 + d
        else:
            normal = n0
        force = mu * normal
        load_torque = force * radius / (p.efficiency * p.gear_ratio)
        if "compliance" in e:
            c = e["compliance"]
            k, beta = c["stiffness_nm_rad"], c["backlash_rad"]
            j_red = p.motor_inertia_kgm2 * j_w / (p.motor_inertia_kgm2 + j_w)
            damping = 2 * c["damping_ratio"] * ca.sqrt(k * j_red)
            twist = x[self._i("twist")]
            rel = omega_m - omega_wheel
            contact = ca.fabs(twist) > beta
            shaft = ca.if_else(contact, k * (twist - ca.sign(twist) * beta) + damping * rel, 0)
            dx[0] = (torque - shaft) / p.motor_inertia_kgm2
            dx[self._i("omega_w")] = (shaft - load_torque) / j_w
            dx[self._i("twist")] = rel
        else:
            dx[0] = (torque - load_torque) / p.equivalent_inertia_kgm2
        resistance = p.running_resistance_n(v_t)
        if "resistance" in e:
            resistance = resistance * e["resistance"]["factor"]
        other = (p.driven_axles - 1) * cfg.mu_required * n0
        dx[1] = (force + other - resistance) / p.train_mass_kg
        return ca.vertcat(*dx), mu, v_s, normal

    def initial_state(self, x0_nominal, torque0: float, t0: float = 0.0) -> np.ndarray:
        """Extra states consistent with the nominal (omega_m, v_t) and torque: no twist transient,
        torque at the command, mu on the curve."""
        cfg, e = self.cfg, self.effects
        p = cfg.params
        x = np.zeros(self.nx)
        x[:2] = x0_nominal[:2]
        if "torque_lag" in e:
            x[self._i("torque_actual")] = torque0
        v_s = float(creep_speed_kmh(p, x0_nominal[0], x0_nominal[1]))
        curve = cfg.fault_curve if t0 >= cfg.fault_time_s else cfg.normal_curve
        mu0 = float(curve.mu_at(v_s, x0_nominal[1]))
        if "rail_curve" in e and t0 >= cfg.fault_time_s:
            rc = e["rail_curve"]
            mu0 = float(rc["peak_mu_scale"] * curve.mu_at(v_s / float(rc["creep_scale"]), x0_nominal[1]))
        if "mu_state" in self.state_names:
            x[self._i("mu_state")] = mu0
        if "bristle" in e:
            x[self._i("bristle_z")] = mu0 / float(e["bristle"]["stiffness_per_m"])
        if "load_transfer_pitch" in e:
            lt = e["load_transfer_pitch"]
            a, b = load_transfer_coefficients(cfg, lt["half_bogie_distance_m"], lt["half_wheelbase_m"],
                                              lt["coupler_height_m"], lt["bogie_height_m"])
            n0 = p.normal_force_n
            x[self._i("normal_dev")] = float((n0 - b) / (1 + a * mu0) - n0)
        if "compliance" in e:
            c = e["compliance"]
            x[self._i("omega_w")] = x0_nominal[0]
            # shaft torque that gives the rotor the same acceleration as the rigid model's
            accel = (torque0 - mu0 * p.torque_per_mu_nm) / p.equivalent_inertia_kgm2
            shaft = torque0 - p.motor_inertia_kgm2 * accel
            x[self._i("twist")] = shaft / float(c["stiffness_nm_rad"]) + math.copysign(float(c["backlash_rad"]), shaft)
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
        if self.q_train > 0:
            v = float(np.round(v / self.q_train) * self.q_train)
        if self.stick is not None:
            k = len(self._hist) - 1                   # this reading's period
            if k < self.stick[0]:
                self._stuck = omega                   # the last reading before the encoder sticks
            elif k < self.stick[1] and self._stuck is not None:
                omega = self._stuck
        return omega, v
