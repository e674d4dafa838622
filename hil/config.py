"""Scenario files (TOML) and every table in them, loaded and checked in one place.

Tables: ``name``/``description``, ``[vehicle]``, ``[curves.normal]``/``[curves.fault]`` (``model = "exp"``,
the default, or, for the fault curve only, ``model = "polach"``: plant/friction.py), ``[run]``,
``[sensors]``, ``[identifier]`` (+ ``[identifier.options.NAME]``), ``[bus]`` (``BusSettings``),
``[plant]`` (an FMU instead of the CasADi model) and ``[reality]`` (effects the nominal model lacks,
checked against ``hil.effects``), ``[control]`` (the TCU's control law, its options and the driver's
demand profile) and ``[[rail]]`` (the rail along the run as segments in time, plant/rail.py).

With ``[[rail]]`` the rail is the segments' curves: ``[curves.fault]`` may be left out, and the run's
"fault" (``fault_time_s``, ``fault_curve``: the first drop the identification figures judge) is the
second segment's start and curve.  ``--set rail.N.KEY=VALUE`` addresses segment N (from 0).  ``parse_set`` turns ``--set TABLE.KEY=VALUE`` items into the
overrides ``load_scenario`` applies over the file.

Every problem is one ``ConfigError`` (alias ``ScenarioError``) line naming the file and the field, e.g.
``scenarios/x.toml: [run] fault_time_s: must be >= 0, got -1``.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from identifier.settings import IdentifierSettings, VehicleModel
from plant import (FrictionCurve, PlantConfig, PolachCurve, SensorConfig, WheelsetParams, equilibrium,
                   train_speed_before_fault)
from plant.rail import DemandProfile, RailSchedule, RailSegment, Recovery

from .errors import ConfigError, ScenarioError

__all__ = ["BusSettings", "ConfigError", "RunConfig", "Scenario", "ScenarioError", "load_scenario", "parse_scenario",
           "parse_set", "resolved_table", "scenario_digest", "scenario_from_handover"]


@dataclass(frozen=True)
class BusSettings:
    """The scenario's optional ``[bus]`` table."""
    bitrate: int = 1_000_000              # arbitration bit rate, bit/s (for the bus-load figure)
    data_bitrate: int = 5_000_000         # CAN FD data-phase bit rate, bit/s
    heartbeat_period_s: float = 0.002     # wall-clock period of the heartbeats, both ways
    silence_periods: int = 25             # realtime: peer silent after this many heartbeat periods (50 ms:
                                          # what a general-purpose OS holds; a shorter stall never ends a run)
    lockstep_silence_s: float = 1.0       # lockstep: peer silent after this many wall seconds
    lockstep_progress_s: float = 5.0      # lockstep: no command for the pending step after this many wall
                                          # seconds: the sensor frame is sent again, after as many more the
                                          # run ends (exit 3) naming the step and the likely cause
    startup_timeout_s: float = 60.0       # wait for the other side's first frame
    lockstep_spin_s: float = 0.002        # lockstep: poll the bus this long before sleeping in it (waking a
                                          # sleeper costs tens of us a frame; 0: always sleep)
    deadline_fraction: float = 0.9        # realtime: the command is due this far into the period
    max_missed_fraction: float = 0.01     # realtime: a run missing more deadlines than this fraction of its
                                          # steps ends with exit 5 (after the logs are written)
    rt_priority: int = 0                  # realtime: SCHED_FIFO priority for plant, hub and TCU (0: off)
    cpu_latency_us: int = 0               # realtime: CPU latency request held for the run (hil/rt/cpu_latency.py;
                                          # 0: idle CPUs poll instead of halting; -1: do not ask)
    idle_spin: str = "auto"               # realtime: a SCHED_IDLE spinner per CPU for the run (hil/rt/idle_spin.py):
                                          # "on", "off", or "auto": on in SCHED_FIFO runs when the CPU latency
                                          # request cannot keep idle CPUs polling (not held, or no cpuidle driver)
    idle_spin_rest_ms: float = 5.0        # each spinner sleeps this long every 100 ms (a host's CPU quota)
    cpu_affinity_plant: tuple = ()        # CPUs the plant process runs on (empty: no setting)
    cpu_affinity_tcu: tuple = ()          # CPUs the TCU process runs on (empty: no setting)
    lockstep_pin: bool = True             # lockstep, neither affinity set: plant and TCU process on two
                                          # different CPUs (hil.session.node_cpus)
    auth: str = "auto"                    # frame authentication (hil/bus/secoc.py): "on", "off", or "auto": on
                                          # for the embedded buses (local, localbus), off otherwise (also
                                          # inprocess: no other node can put a frame on it)
    auth_key_file: str = ""               # the key (32 hex digits); "": a new key per run, made by the run
    dbc: str = ""                         # a TCU's own DBC (path relative to the scenario file); "": hil/hil.dbc
    mapping: tuple = ()                   # [bus.mapping]: (quantity, "Message.Signal") pairs on that DBC
                                          # (hil/bus/mapping.py)


@dataclass(frozen=True)
class RunConfig:
    mu_required: float
    fault_time_s: float
    duration_s: float
    initial_train_speed_ms: float
    integration_step_s: float
    exchange_period_s: float
    seed: int = 1


@dataclass(frozen=True)
class ControlSettings:
    """The scenario's optional ``[control]`` table: the TCU's control law (identifier/control), its options
    by law, and the driver's demand profile (None: the paper's constant demand, the equilibrium torque)."""
    law: str = "demand"
    demand: DemandProfile | None = None
    options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Scenario:
    name: str
    path: str
    source_text: str
    description: str
    vehicle: WheelsetParams
    normal_curve: FrictionCurve
    fault_curve: FrictionCurve | PolachCurve         # [curves.fault] model = "exp" (default) or "polach"
    run: RunConfig
    sensors: SensorConfig
    identifier: dict = field(default_factory=dict)   # overrides of IdentifierSettings defaults
    extra: dict = field(default_factory=dict)         # the raw [plant], [reality] and [bus] tables
    overrides: dict = field(default_factory=dict)     # --set TABLE.KEY=VALUE applied over source_text
    bus: BusSettings = field(default_factory=BusSettings)
    control: ControlSettings = field(default_factory=ControlSettings)
    rail: RailSchedule | None = None                  # [[rail]]: the rail along the run

    def plant_config(self) -> PlantConfig:
        r = self.run
        return PlantConfig(self.vehicle, self.normal_curve, self.fault_curve, r.mu_required, r.fault_time_s,
                           r.initial_train_speed_ms, r.integration_step_s, r.exchange_period_s, self.rail,
                           self.control.demand)

    def demand_torque_nm(self, t_s: float) -> float:
        """The driver's demand as motor torque at ``t_s``: ``mu_d(t) * torque_per_mu_nm`` with a demand
        profile, else the paper's constant demand (the equilibrium torque the TCU commands)."""
        if self.control.demand is None:
            return self.identifier_settings().torque_demand_nm
        return self.control.demand.at(t_s) * self.vehicle.torque_per_mu_nm

    def identifier_settings(self) -> IdentifierSettings:
        v = self.vehicle
        _, torque = equilibrium(self.plant_config())
        vehicle = VehicleModel(v.equivalent_inertia_kgm2, v.torque_per_mu_nm, v.gear_ratio, v.wheel_radius_m)
        overrides = dict(self.identifier)
        options = overrides.pop("options", {})
        return IdentifierSettings(period_s=self.run.exchange_period_s, vehicle=vehicle, torque_demand_nm=torque,
                                  initial_guess=tuple(self.normal_curve.params), options=options, **overrides)

    @property
    def steps(self) -> int:
        return int(round(self.run.duration_s / self.run.exchange_period_s))

    @functools.cached_property
    def digest(self) -> str:
        """SHA-256 (hex) of the resolved scenario (``scenario_digest``): equal on both sides of a run."""
        return scenario_digest(self.source_text, self.path, self.overrides)

    def handover(self) -> dict:
        """What a TCU process needs to run exactly this scenario (``scenario_from_handover``): the text, its
        path (a ``[bus] dbc`` is found beside it), the overrides, and the digest they resolve to.  JSON."""
        return {"format": HANDOVER_FORMAT, "path": self.path, "text": self.source_text,
                "overrides": dict(self.overrides), "digest": self.digest}


# -- validation ---------------------------------------------------------------------------------
#: [vehicle] field -> (lowest, highest) accepted: wide around any railway vehicle, narrow enough that the
#: plant's equations (divisions by the gear ratio, the efficiency, the inertia) stay finite
VEHICLE_RANGES = {
    "axle_load_kg": (100.0, 1e6), "motor_inertia_kgm2": (1e-4, 1e5), "wheelset_inertia_kgm2": (1e-3, 1e6),
    "wheel_radius_m": (0.05, 5.0), "train_mass_kg": (100.0, 1e8), "gravity_ms2": (0.1, 100.0),
    "gear_ratio": (0.05, 100.0), "efficiency": (0.01, 1.0), "half_bogie_distance_m": (1e-3, 1e3),
    "half_wheelbase_m": (1e-3, 1e3), "coupler_height_m": (1e-3, 1e3), "bogie_height_m": (1e-3, 1e3),
    "driven_axles": (1, 10_000), "davis_a_n": (0.0, 1e8), "davis_b_n_per_ms": (0.0, 1e8),
    "davis_c_n_per_ms2": (0.0, 1e8),
}
#: a run of more integration steps (duration_s / integration_step_s) is refused at load
MAX_INTEGRATION_STEPS = 100_000_000
#: a strategy (or the drill) with more particles is refused at load
MAX_PARTICLES = 1_000_000
#: strategy options that size arrays at construction -> the largest value accepted
OPTION_CAPS = {"particles": MAX_PARTICLES, "noise_block": 1024, "moves_drawn_ahead": 1024, "prelim_grid": 64,
               "prelim_iterations": 10_000, "projection_iterations": 1000, "max_samples": 1_000_000,
               "baseline_readings": 1_000_000, "fit_window": 1_000_000, "report_samples": 1_000_000,
               "window_samples": 100_000}
#: a strategy's particles x noise_block (transition-noise draws made ahead, 5 doubles each) above this
#: is refused at load (8e8 doubles: 6.4 GB)
MAX_NOISE_DRAWS = 100_000_000
#: [identifier] field -> (lowest, highest) accepted
IDENTIFIER_RANGES = {
    "observer_pole_rad_s": (1e-3, 1e6), "detection_creep_rise_kmh": (0.0, 100.0), "baseline_samples": (2, 1_000_000),
    "settle_time_s": (0.0, 3600.0), "window_samples": (1, 100_000), "k_pe": (0.0, 1e6), "c_lw": (0.0, 1e6),
    "c_up": (0.0, 1e6), "max_corrections": (1, 1_000_000),
    "drill_particles": (None, MAX_PARTICLES),       # 0 or >= 2: IdentifierSettings says so
}
#: [bus] field -> (lowest, highest) accepted
BUS_RANGES = {
    "bitrate": (1_000, 100_000_000), "data_bitrate": (1_000, 100_000_000), "heartbeat_period_s": (1e-4, 10.0),
    "silence_periods": (1, 1_000_000), "lockstep_silence_s": (1e-3, 86_400.0),
    "lockstep_progress_s": (1e-3, 86_400.0), "startup_timeout_s": (1e-3, 86_400.0), "lockstep_spin_s": (0.0, 1.0),
    "deadline_fraction": (1e-3, 0.999), "rt_priority": (0, 99), "max_missed_fraction": (0.0, 1.0),
    "cpu_latency_us": (-1, 2_000_000_000), "idle_spin_rest_ms": (0.0, 100.0),
}
#: the PlantSensor signals' ranges in hil/hil.dbc (motor speed rad/s, train speed m/s); a scenario whose
#: speeds at the start, with six standard deviations of sensor noise, leave them is refused at load
DBC_MOTOR_SPEED_RAD_S = 2000.0
DBC_TRAIN_SPEED_MS = 200.0


def _in_range(path, where, value, bounds) -> None:
    """``bounds`` (lo, hi); lo None: only the ceiling is checked here (the floor elsewhere)."""
    lo, hi = bounds
    if lo is None:
        _check(path, where, value <= hi, f"must be at most {hi:g}", value)
    else:
        _check(path, where, lo <= value <= hi, f"must be in [{lo:g}, {hi:g}]", value)


_IDENTIFIER_FIELDS = {f.name: f for f in dataclasses.fields(IdentifierSettings)
                      if f.name not in ("period_s", "vehicle", "torque_demand_nm", "initial_guess")}
_OPTIONAL_TABLES = ("plant", "reality", "bus")
PLANT_KEYS = ("fmu", "mapping", "parameters")


#: the longest message part ``_fail`` keeps (a huge value quoted in it is cut)
MESSAGE_MAX = 300


def _fail(path, where, msg) -> ScenarioError:
    msg = str(msg).replace("\n", " ")
    if len(msg) > MESSAGE_MAX:
        msg = msg[:MESSAGE_MAX] + "..."
    return ScenarioError(f"{path}: {where}: {msg}")


def _coerce(path, where, value, typ):
    if typ in (float, "float"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(path, where, f"must be a number, got {value!r}")
        if not math.isfinite(value):
            raise _fail(path, where, f"must be finite, got {value!r}")
        return float(value)
    if typ in (int, "int"):
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(path, where, f"must be an integer, got {value!r}")
        return value
    if typ in (bool, "bool"):
        if not isinstance(value, bool):
            raise _fail(path, where, f"must be true or false, got {value!r}")
        return value
    if typ in (str, "str"):
        if not isinstance(value, str):
            raise _fail(path, where, f"must be a string, got {value!r}")
        return value
    if typ in (dict, "dict"):
        if not isinstance(value, dict):
            raise _fail(path, where, f"must be a table, got {value!r}")
        return value
    raise TypeError(typ)


def _table(path, data: dict, name: str, cls, required: bool = True) -> dict:
    if name not in data:
        if required:
            raise _fail(path, f"[{name}]", "missing table")
        return {}
    table = data[name]
    if not isinstance(table, dict):
        raise _fail(path, f"[{name}]", "must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = {}
    for key, value in table.items():
        if key not in fields:
            raise _fail(path, f"[{name}] {key}", f"unknown key (known: {', '.join(fields)})")
        out[key] = _coerce(path, f"[{name}] {key}", value, fields[key].type)
    for key, f in fields.items():
        if key not in out and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise _fail(path, f"[{name}] {key}", "missing field")
    return out


def _check(path, where, ok: bool, msg: str, value):
    if not ok:
        raise _fail(path, where, f"{msg}, got {value!r}")


EXP_KEYS = ("model", "lambda0", "lambdas", "taus")
POLACH_KEYS = ("model",) + PolachCurve.KEYS
CURVE_MODELS = ("exp", "polach")


def _curve(path, data, key, polach_speed=None) -> FrictionCurve | PolachCurve:
    """``[curves.KEY]``: ``model = "exp"`` (the default: lambda0, lambdas, taus) or ``model = "polach"``
    (plant/friction.py PolachCurve's keys; ``reference_train_speed_ms`` optional, default
    ``polach_speed()``: the train speed at the fault).  ``polach_speed`` None: this curve must be exp."""
    curves = data.get("curves")
    if not isinstance(curves, dict):
        raise _fail(path, "[curves]", "missing table")
    if key not in curves or not isinstance(curves[key], dict):
        raise _fail(path, f"[curves.{key}]", "missing table")
    t = curves[key]
    where = f"[curves.{key}]"
    model = _coerce(path, f"{where} model", t.get("model", "exp"), str)
    if model not in CURVE_MODELS:
        raise _fail(path, f"{where} model", f"unknown friction law {model!r} (known: {', '.join(CURVE_MODELS)})")
    if model == "polach":
        if polach_speed is None:
            raise _fail(path, f"{where} model", "must be 'exp' (the exponential form: the equilibrium and the "
                        "identifier's initial guess need it), got 'polach'")
        curve = _polach_curve(path, t, key, where, polach_speed)
    else:
        curve = _exp_curve(path, t, key, where)
    v_peak, mu_peak = curve.peak()
    _check(path, where, mu_peak > 0 and 0 < v_peak < 29, "must rise to a positive peak inside 0-29 km/h",
           (v_peak, mu_peak))
    return curve


def _exp_curve(path, t, key, where) -> FrictionCurve:
    for k in t:
        if k not in EXP_KEYS:
            raise _fail(path, f"{where} {k}", f"unknown key (known: {', '.join(EXP_KEYS)})")
    for k in ("lambda0", "lambdas", "taus"):
        if k not in t:
            raise _fail(path, f"{where} {k}", "missing field")
    lam0 = _coerce(path, f"{where} lambda0", t["lambda0"], float)
    lists = {}
    for k in ("lambdas", "taus"):
        if not isinstance(t[k], list) or not t[k]:
            raise _fail(path, f"{where} {k}", f"must be a non-empty list of numbers, got {t[k]!r}")
        lists[k] = tuple(_coerce(path, f"{where} {k}", x, float) for x in t[k])
    _check(path, f"{where} taus", len(lists["taus"]) == len(lists["lambdas"]), "must have as many entries as lambdas",
           t["taus"])
    _check(path, f"{where} taus", all(x < 0 for x in lists["taus"]), "must all be negative (decaying terms)",
           t["taus"])
    return FrictionCurve(lam0, lists["lambdas"], lists["taus"], key)


def _polach_curve(path, t, key, where, polach_speed) -> PolachCurve:
    for k in t:
        if k not in POLACH_KEYS:
            raise _fail(path, f"{where} {k}", f"unknown key for model 'polach' (known: {', '.join(POLACH_KEYS)})")
    v = {}
    for k in PolachCurve.KEYS:
        if k not in t:
            if k == "reference_train_speed_ms":
                continue
            raise _fail(path, f"{where} {k}", "missing field")
        v[k] = _coerce(path, f"{where} {k}", t[k], float)
    _check(path, f"{where} mu_static", v["mu_static"] > 0, "must be > 0", v["mu_static"])
    _check(path, f"{where} A", 0 < v["A"] <= 1, "must be in (0, 1]", v["A"])
    _check(path, f"{where} B_s_per_m", v["B_s_per_m"] >= 0, "must be >= 0", v["B_s_per_m"])
    _check(path, f"{where} k_A", 0 < v["k_A"] <= 1, "must be in (0, 1]", v["k_A"])
    _check(path, f"{where} k_S", 0 < v["k_S"] <= v["k_A"], "must be in (0, k_A]", v["k_S"])
    _check(path, f"{where} stiffness", v["stiffness"] > 0, "must be > 0", v["stiffness"])
    if "reference_train_speed_ms" in v:
        _check(path, f"{where} reference_train_speed_ms", v["reference_train_speed_ms"] > 0, "must be > 0",
               v["reference_train_speed_ms"])
    else:
        v["reference_train_speed_ms"] = polach_speed()
    return PolachCurve(**v, name=key)


def resolved_table(text: str, path: str = "<scenario>", overrides: dict | None = None) -> dict:
    """The scenario's TOML table with ``overrides`` (``--set`` items, ``parse_set``) applied: what both the
    plant and the TCU run (``scenario_digest``).  ``ScenarioError``/``ConfigError`` naming the field."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{path}: not valid TOML: {e}") from None
    except RecursionError:
        raise ScenarioError(f"{path}: not a scenario: arrays or tables nested too deep to read") from None
    for dotted, value in (overrides or {}).items():
        *tables, key = dotted.split(".")
        node = data
        for i, t in enumerate(tables):
            if isinstance(node, list):          # rail.N: the N-th segment (from 0)
                if not (t.isdigit() and int(t) < len(node)):
                    raise ConfigError(f"--set {dotted}: {'.'.join(tables[:i])} has segments 0..{len(node) - 1} in "
                                      f"{path}, not {t!r}")
                node = node[int(t)]
            else:
                node = node.setdefault(t, {})
            if not isinstance(node, (dict, list)):
                raise ConfigError(f"--set {dotted}: {'.'.join(tables[:i + 1])} is not a table in {path}")
        if isinstance(node, list):
            raise ConfigError(f"--set {dotted}: {'.'.join(tables)} is a list of segments in {path}; name one "
                              f"(e.g. {'.'.join(tables)}.0.{key})")
        node[key] = value
    return data


#: ``[bus]`` keys a run's session hands the TCU process itself (its frame key, its CPUs): plumbing of this
#: run, not part of the scenario both sides must agree on
SESSION_BUS_KEYS = ("auth", "auth_key_file", "cpu_affinity_tcu", "cpu_affinity_plant")
#: the hand-over file's format (``Scenario.handover``)
HANDOVER_FORMAT = 1


def scenario_digest(text: str, path: str = "<scenario>", overrides: dict | None = None) -> str:
    """SHA-256 (hex) of the resolved scenario: ``resolved_table`` as canonical JSON (sorted keys, no
    whitespace), less ``SESSION_BUS_KEYS``.  Two sides run the same scenario exactly when their digests are
    equal, however they got there (a file with the value in it, or another file and ``--set``); the file's
    path and layout, comments and key order do not count."""
    import hashlib
    import json

    data = resolved_table(text, path, overrides)
    bus = data.get("bus")
    if isinstance(bus, dict):
        data["bus"] = {k: v for k, v in bus.items() if k not in SESSION_BUS_KEYS}
        if not data["bus"]:          # a [bus] made by those keys alone is no table of the scenario's
            del data["bus"]
    canonical = json.dumps(data, sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=str)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def scenario_from_handover(data: dict, where: str = "hand-over") -> "Scenario":
    """The scenario a ``Scenario.handover`` dict describes, checked against the digest it carries (a
    hand-over file cut or edited on the way is one ``ConfigError``)."""
    try:
        fmt, path, text, overrides, digest = (data["format"], data["path"], data["text"], data["overrides"],
                                              data["digest"])
    except (KeyError, TypeError):
        raise ConfigError(f"{where}: not a scenario hand-over (format, path, text, overrides, digest)") from None
    if fmt != HANDOVER_FORMAT or not isinstance(text, str) or not isinstance(overrides, dict):
        raise ConfigError(f"{where}: a scenario hand-over of format {fmt!r}; this version reads {HANDOVER_FORMAT}")
    scenario = parse_scenario(text, str(path), overrides)
    if scenario.digest != digest:
        raise ConfigError(f"{where}: the scenario resolves to digest {scenario.digest[:16]}, the hand-over says "
                          f"{str(digest)[:16]}")
    return scenario


def parse_scenario(text: str, path: str = "<scenario>", overrides: dict | None = None, *,
                   check_dbc: bool = True) -> Scenario:
    """The scenario in ``text`` (read from ``path``), checked; ``check_dbc`` False: a ``[bus] dbc`` is not
    opened (a log's scenario: the run is over, the log keeps the DBC it ran with)."""
    data = resolved_table(text, path, overrides)
    known = {"name", "description", "vehicle", "curves", "run", "sensors", "identifier", *_OPTIONAL_TABLES,
             "control", "rail"}
    for key in data:
        if key not in known:
            raise _fail(path, key, f"unknown key (known: {', '.join(sorted(known))})")
    name = _coerce(path, "name", data.get("name", Path(path).stem), str)
    _check(path, "name", name.isprintable(), "must be printable text (no control characters)", name[:80])
    description = _coerce(path, "description", data.get("description", ""), str)
    vehicle = WheelsetParams(**_table(path, data, "vehicle", WheelsetParams, required=False))
    for f in dataclasses.fields(vehicle):
        _in_range(path, f"[vehicle] {f.name}", getattr(vehicle, f.name), VEHICLE_RANGES[f.name])

    control_raw = data.get("control", {})
    if not isinstance(control_raw, dict):
        raise _fail(path, "[control]", "must be a table")
    demand = _demand(path, control_raw)
    run_table = data.get("run")
    segmented = "rail" in data
    if isinstance(run_table, dict):        # the first demand and the rail's first change fill in what is left out
        if demand is not None:
            run_table.setdefault("mu_required", demand.demand_mu[0])
        if segmented and isinstance(data["rail"], list) and len(data["rail"]) > 1 \
                and isinstance(data["rail"][1], dict) and "start_s" in data["rail"][1]:
            start = _coerce(path, "[[rail]] 1 start_s", data["rail"][1]["start_s"], float)
            _check(path, "[[rail]] 1 start_s", start > 0.0, "must be > 0 (a segment after the run's end never comes)",
                   start)
            run_table.setdefault("fault_time_s", start)
    run = RunConfig(**_table(path, data, "run", RunConfig))
    _check(path, "[run] mu_required", 0 < run.mu_required < 1, "must be in (0, 1)", run.mu_required)
    _check(path, "[run] fault_time_s", run.fault_time_s >= 0, "must be >= 0", run.fault_time_s)
    _check(path, "[run] duration_s", run.duration_s > run.fault_time_s, "must be after fault_time_s", run.duration_s)
    _check(path, "[run] initial_train_speed_ms", run.initial_train_speed_ms > 0, "must be > 0",
           run.initial_train_speed_ms)
    _check(path, "[run] integration_step_s", 0 < run.integration_step_s <= 1e-2, "must be in (0, 0.01]",
           run.integration_step_s)
    ratio = run.exchange_period_s / run.integration_step_s
    _check(path, "[run] exchange_period_s", run.exchange_period_s > 0 and abs(ratio - round(ratio)) < 1e-6
           and round(ratio) >= 1, "must be a positive whole multiple of integration_step_s", run.exchange_period_s)
    _check(path, "[run] seed", 0 <= run.seed < 2 ** 63, "must be in [0, 2^63)", run.seed)
    _check(path, "[run] initial_train_speed_ms", run.initial_train_speed_ms < DBC_TRAIN_SPEED_MS,
           f"must be below {DBC_TRAIN_SPEED_MS:g} (the PlantSensor frame's range)", run.initial_train_speed_ms)
    steps = run.duration_s / run.integration_step_s
    if steps > MAX_INTEGRATION_STEPS:
        raise _fail(path, "[run] duration_s", f"{run.duration_s:g} s at integration_step_s {run.integration_step_s:g} "
                    f"is {steps:.3g} integration steps; more than {MAX_INTEGRATION_STEPS:.0e} are refused")

    sensors = SensorConfig(**_table(path, data, "sensors", SensorConfig, required=False))
    for f in dataclasses.fields(sensors):
        _check(path, f"[sensors] {f.name}", getattr(sensors, f.name) >= 0, "must be >= 0", getattr(sensors, f.name))
    _check_dbc_ranges(path, vehicle, run, sensors)

    curves = data.get("curves")
    if curves is not None and not isinstance(curves, dict):
        raise _fail(path, "[curves]", f"must be a table holding [curves.normal] and [curves.fault], got {curves!r}")
    for key in ("normal", "fault"):
        if curves is not None and key in curves and not isinstance(curves[key], dict):
            raise _fail(path, f"[curves.{key}]", f"must be a table, got {curves[key]!r}")
    normal = _curve(path, data, "normal")
    rail = _rail(path, data, vehicle, run) if segmented else None
    if rail is None:
        fault = _curve(path, data, "fault", lambda: float(train_speed_before_fault(
            vehicle, run.mu_required, run.initial_train_speed_ms, run.fault_time_s)))
    else:
        if isinstance(curves, dict) and "fault" in curves:
            raise _fail(path, "[curves.fault]", "leave it out with [[rail]]: the rail's segments are the run's curves")
        fault = rail.segments[1].curve
        _check(path, "[run] fault_time_s", run.fault_time_s == rail.segments[1].start_s,
               f"must be the second rail segment's start {rail.segments[1].start_s:g} with [[rail]] (or left out)",
               run.fault_time_s)
    first = normal if rail is None else rail.segments[0].curve
    try:
        first.creep_for_mu(run.mu_required)
    except ValueError:
        what = "NFCC-0" if rail is None else "the first rail segment"
        raise _fail(path, "[run] mu_required", f"{what} never reaches {run.mu_required} on its stable side "
                    f"(its peak is {first.peak()[1]:.4f})") from None

    ident_raw = data.get("identifier", {})
    if not isinstance(ident_raw, dict):
        raise _fail(path, "[identifier]", "must be a table")
    identifier = {}
    for key, value in ident_raw.items():
        if key not in _IDENTIFIER_FIELDS:
            raise _fail(path, f"[identifier] {key}", f"unknown key (known: {', '.join(_IDENTIFIER_FIELDS)})")
        typ = _IDENTIFIER_FIELDS[key].type
        if key == "excitation":
            from identifier.excitation import Excitation
            try:
                Excitation.from_dict(value)
            except ValueError as e:
                raise _fail(path, "[identifier.excitation]", e) from None
            identifier[key] = dict(value)
            continue
        identifier[key] = value if key == "options" and isinstance(value, dict) else \
            _coerce(path, f"[identifier] {key}", value, typ)
        if key in IDENTIFIER_RANGES:
            _in_range(path, f"[identifier] {key}", identifier[key], IDENTIFIER_RANGES[key])
    bus = _bus(path, data)
    _plant(path, data)
    _reality(path, data)
    extra = {k: data[k] for k in _OPTIONAL_TABLES if k in data}
    control = _control(path, control_raw, demand, segmented)
    if rail is not None:
        for table in ("reality", "plant"):
            if data.get(table):
                raise _fail(path, f"[{table}]", "not with [[rail]] yet: the rail's segments run on the CasADi plant "
                            "without reality effects")
    scenario = Scenario(name, path, text, description, vehicle, normal, fault, run, sensors, identifier, extra,
                        dict(overrides or {}), bus, control, rail)
    try:
        scenario.identifier_settings()
        from identifier.observer import LoadTorqueObserver
        LoadTorqueObserver(1.0, run.exchange_period_s, scenario.identifier_settings().observer_pole_rad_s)
    except (ValueError, ArithmeticError) as e:
        raise _fail(path, "[identifier]", e) from None
    _check_strategy_options(path, scenario)
    if check_dbc:
        _check_mapping(path, scenario)
    return scenario


def _check_mapping(path, scenario) -> None:
    """``[bus] dbc`` and ``[bus.mapping]`` together, checked against their DBC and this scenario's ranges
    (``hil.bus.mapping.load_mapping``); a mapped bus runs unauthenticated."""
    bus = scenario.bus
    if not bus.dbc and not bus.mapping:
        return
    if not bus.dbc:
        raise _fail(path, "[bus.mapping]", "needs [bus] dbc, the DBC whose messages it names")
    if bus.auth == "on":
        raise _fail(path, "[bus] auth", "\"on\" is not possible with [bus] dbc: a TCU's own DBC has no "
                    "authentication trailer (a mapped bus runs unauthenticated)")
    from .bus.mapping import load_mapping, needed_ranges

    load_mapping(path, bus.dbc, dict(bus.mapping), scenario.run.exchange_period_s, needed_ranges(scenario))


#: [[rail]] segment keys besides a curve's (``model`` and its keys, or ``peak_mu`` and ``peak_creep_kmh`` with
#: an optional exp shape, or ``family`` with ``seed`` and ``index``)
SEGMENT_KEYS = ("start_s", "transition_s", "label", "recovers_to", "energy_clean_j")
PEAK_KEYS = ("peak_mu", "peak_creep_kmh", "mu0", "asymptote_ratio", "term_ratio")
FAMILY_KEYS = ("family", "seed", "index")
#: the exp shape a segment given by its peak takes when it names none (a wet rail's; plant/families.py)
PEAK_SHAPE_DEFAULTS = {"mu0": 0.0, "asymptote_ratio": 0.35, "term_ratio": 2.2}
CONTROL_KEYS = ("law", "demand_mu", "options")


def _demand(path, table) -> DemandProfile | None:
    """``[control] demand_mu = [[t_s, mu], ...]``: the driver's demand profile, or None."""
    if "demand_mu" not in table:
        return None
    pts = table["demand_mu"]
    where = "[control] demand_mu"
    if not isinstance(pts, list) or not pts or not all(isinstance(p, list) and len(p) == 2 for p in pts):
        raise _fail(path, where, f"must be a list of [t_s, mu] points, got {pts!r}")
    times = tuple(_coerce(path, where, p[0], float) for p in pts)
    mus = tuple(_coerce(path, where, p[1], float) for p in pts)
    _check(path, where, times[0] == 0.0, "must start at t = 0", pts[0])
    _check(path, where, all(b >= a for a, b in zip(times, times[1:])), "times must not decrease", list(times))
    _check(path, where, all(0.0 <= m < 1.0 for m in mus), "demands must be in [0, 1) (equivalent mu)", list(mus))
    return DemandProfile(times, mus)


def _control(path, table, demand, segmented: bool) -> ControlSettings:
    from identifier.control import LAWS, check_options

    for key in table:
        if key not in CONTROL_KEYS:
            raise _fail(path, f"[control] {key}", f"unknown key (known: {', '.join(CONTROL_KEYS)})")
    if segmented and "law" not in table:
        raise _fail(path, "[control] law", f"a scenario with [[rail]] names its control law (known: {', '.join(LAWS)})")
    law = _coerce(path, "[control] law", table.get("law", "demand"), str)
    if law not in LAWS:
        raise _fail(path, "[control] law", f"unknown control law {law!r} (known: {', '.join(LAWS)})")
    options = table.get("options", {})
    if not isinstance(options, dict):
        raise _fail(path, "[control.options]", "must be a table of tables, one per law")
    for name, opts, where in _named_tables(path, "control.options", options, LAWS, "control law"):
        try:
            check_options(name, opts)
        except ValueError as e:
            raise _fail(path, where, e) from None
    return ControlSettings(law, demand, {k: dict(v) for k, v in options.items()})


def _rail(path, data, vehicle, run) -> RailSchedule:
    """``[[rail]]``: segments in time, each with a curve (module docstring, plant/rail.py)."""
    from plant.families import FAMILIES, draw_rng, exp_coefficients, sample_curves

    segs = data["rail"]
    if not isinstance(segs, list) or len(segs) < 2 or not all(isinstance(t, dict) for t in segs):
        raise _fail(path, "[[rail]]", "must be at least two segments ([[rail]] tables): the rail changes along the run")
    segments, recovery = [], {}
    for i, t in enumerate(segs):
        where = f"[[rail]] {i}"
        curve_keys = set(t) - set(SEGMENT_KEYS)
        start = _coerce(path, f"{where} start_s", t.get("start_s", math.nan if i else 0.0), float) \
            if "start_s" in t or i == 0 else None
        if start is None:
            raise _fail(path, f"{where} start_s", "missing field")
        _check(path, f"{where} start_s", (start == 0.0) if i == 0 else (start > 0.0 and math.isfinite(start)),
               "must be 0 for the first segment" if i == 0 else "must be > 0 (a segment after the run's end never "
               "comes)", start)
        transition = _coerce(path, f"{where} transition_s", t.get("transition_s", 0.0), float)
        _check(path, f"{where} transition_s", transition >= 0.0 and not (i == 0 and transition > 0.0),
               "must be >= 0 (and 0 for the first segment)", transition)
        label = _coerce(path, f"{where} label", t.get("label", ""), str)
        speed = float(train_speed_before_fault(vehicle, run.mu_required, run.initial_train_speed_ms, start))
        name = label or f"rail{i}"
        if "family" in t:
            for k in curve_keys:
                if k not in FAMILY_KEYS:
                    raise _fail(path, f"{where} {k}", f"unknown key for a drawn curve (known: {', '.join(FAMILY_KEYS)})")
            family = _coerce(path, f"{where} family", t["family"], str)
            if family not in FAMILIES:
                raise _fail(path, f"{where} family", f"unknown family {family!r} (known: {', '.join(FAMILIES)})")
            seed, index = (_coerce(path, f"{where} {k}", t.get(k, 0), int) for k in ("seed", "index"))
            _check(path, f"{where} seed", seed >= 0 and index >= 0, "seed and index must be >= 0", (seed, index))
            curve = sample_curves(family, 1, draw_rng(family, seed, index), speed).curve(0, name)
        elif "peak_mu" in t or "peak_creep_kmh" in t:
            for k in curve_keys:
                if k not in PEAK_KEYS:
                    raise _fail(path, f"{where} {k}", f"unknown key for a curve given by its peak (known: "
                                f"{', '.join(PEAK_KEYS)})")
            v = {k: _coerce(path, f"{where} {k}", t[k], float) if k in t else PEAK_SHAPE_DEFAULTS.get(k)
                 for k in PEAK_KEYS}
            for k in ("peak_mu", "peak_creep_kmh"):
                if v[k] is None:
                    raise _fail(path, f"{where} {k}", "missing field")
            _check(path, f"{where} peak_mu", 0.0 < v["peak_mu"] < 1.0, "must be in (0, 1)", v["peak_mu"])
            _check(path, f"{where} peak_creep_kmh", 0.05 <= v["peak_creep_kmh"] <= 20.0, "must be in [0.05, 20]",
                   v["peak_creep_kmh"])
            _check(path, f"{where} mu0", 0.0 <= v["mu0"] < v["peak_mu"], "must be in [0, peak_mu)", v["mu0"])
            _check(path, f"{where} asymptote_ratio", 0.0 <= v["asymptote_ratio"] <= 0.9, "must be in [0, 0.9]",
                   v["asymptote_ratio"])
            _check(path, f"{where} term_ratio", 1.1 <= v["term_ratio"] <= 10.0, "must be in [1.1, 10]", v["term_ratio"])
            l0, l1, l2, t1, t2 = (float(x) for x in exp_coefficients(v["peak_mu"], v["peak_creep_kmh"], v["mu0"],
                                                                      v["asymptote_ratio"], v["term_ratio"]))
            curve = FrictionCurve(l0, (l1, l2), (t1, t2), name)
        else:
            curve = _curve(path, {"curves": {name: {k: t[k] for k in curve_keys}}}, name, lambda: speed)
        if "family" in t or "peak_mu" in t:
            v_peak, mu_peak = curve.peak()
            _check(path, where, mu_peak > 0 and 0 < v_peak < 29, "must rise to a positive peak inside 0-29 km/h",
                   (v_peak, mu_peak))
        segments.append(RailSegment(start, curve, transition, label))
        if "recovers_to" in t or "energy_clean_j" in t:
            j = _coerce(path, f"{where} recovers_to", t.get("recovers_to", -1), int)
            _check(path, f"{where} recovers_to", 0 <= j < len(segs) and j != i,
                   "must name another segment (its index from 0) whose curve this one recovers to", j)
            e = _coerce(path, f"{where} energy_clean_j", t.get("energy_clean_j", math.nan), float)
            _check(path, f"{where} energy_clean_j", e > 0, "must be > 0 (J dissipated for 63 % recovery)", e)
            recovery[i] = (j, e)
    for i, (j, e) in recovery.items():
        recovery[i] = Recovery(e, segments[j].curve)
    try:
        return RailSchedule(tuple(segments), recovery)
    except ValueError as e:
        raise _fail(path, "[[rail]]", e) from None


AUTH_MODES = ("auto", "on", "off")
IDLE_SPIN_MODES = ("auto", "on", "off")


def _bus(path, data) -> BusSettings:
    table = data.get("bus", {})
    if not isinstance(table, dict):
        raise _fail(path, "[bus]", "must be a table")
    fields = {f.name: f for f in dataclasses.fields(BusSettings)}
    values = {}
    for key, value in table.items():
        if key not in fields:
            raise _fail(path, f"[bus] {key}", f"unknown key (known: {', '.join(fields)})")
        if key == "auth":
            if value not in AUTH_MODES:
                raise _fail(path, "[bus] auth", f"must be one of {', '.join(AUTH_MODES)}, got {value!r}")
            values[key] = value
            continue
        if key == "idle_spin":
            if value not in IDLE_SPIN_MODES:
                raise _fail(path, "[bus] idle_spin", f"must be one of {', '.join(IDLE_SPIN_MODES)}, got {value!r}")
            values[key] = value
            continue
        if key == "dbc":
            if not isinstance(value, str) or not value:
                raise _fail(path, "[bus] dbc", f"must be the path of a DBC file (a string), got {value!r}")
            values[key] = value
            continue
        if key == "mapping":
            if not isinstance(value, dict):
                raise _fail(path, "[bus.mapping]", "must be a table of QUANTITY = \"Message.Signal\"")
            values[key] = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in value.items()))
            continue
        if key == "auth_key_file":
            if not isinstance(value, str):
                raise _fail(path, "[bus] auth_key_file", f"must be a path (a string), got {value!r}")
            values[key] = value
            continue
        if key == "lockstep_pin":
            if not isinstance(value, bool):
                raise _fail(path, "[bus] lockstep_pin", f"must be true or false, got {value!r}")
            values[key] = value
            continue
        if key.startswith("cpu_affinity_"):
            if not isinstance(value, list) or any(isinstance(c, bool) or not isinstance(c, int) or not 0 <= c < 4096
                                                  for c in value):
                raise _fail(path, f"[bus] {key}", f"must be a list of CPU numbers (0..4095), got {value!r}")
            values[key] = tuple(value)
            continue
        lo = BUS_RANGES[key][0]       # the sign a number must have follows from its range's floor
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or not (lo < 0 or (value >= 0 if lo == 0 else value > 0)):
            kind = "" if lo < 0 else "non-negative " if lo == 0 else "positive "
            raise _fail(path, f"[bus] {key}", f"must be a {kind}number, got {value!r}")
        if fields[key].type == "int" and not isinstance(value, int):
            raise _fail(path, f"[bus] {key}", f"must be an integer, got {value!r}")
        _in_range(path, f"[bus] {key}", value, BUS_RANGES[key])
        values[key] = value
    return BusSettings(**values)


def _plant(path, data) -> None:
    """The ``[plant]`` table's shape (the FMU itself is opened by ``hil.plants``)."""
    table = data.get("plant", {})
    if not isinstance(table, dict):
        raise _fail(path, "[plant]", "must be a table")
    for key in table:
        if key not in PLANT_KEYS:
            raise _fail(path, f"[plant] {key}", f"unknown key (known: {', '.join(PLANT_KEYS)})")
    if "fmu" in table and not isinstance(table["fmu"], str):
        raise _fail(path, "[plant] fmu", f"must be a path string, got {table['fmu']!r}")
    for key in ("mapping", "parameters"):
        if key in table and not isinstance(table[key], dict):
            raise _fail(path, f"[plant.{key}]", f"must be a table, got {table[key]!r}")
    for role, name in table.get("mapping", {}).items():
        if not isinstance(name, str):
            raise _fail(path, f"[plant.mapping] {role}", f"must be an FMU variable name, got {name!r}")
    for name, value in table.get("parameters", {}).items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(path, f"[plant.parameters] {name}", f"must be a number, got {value!r}")


def _reality(path, data) -> None:
    from .effects import effects_from_table

    try:
        effects_from_table(data.get("reality") or {}, f"{path}: [reality]")
    except ValueError as e:
        raise ConfigError(str(e)) from None


def parse_set(items) -> dict:
    """``["run.duration_s=600"]`` -> ``{"run.duration_s": 600}``; values are read as TOML scalars
    (a value TOML cannot read stays a string)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected TABLE.KEY=VALUE")
        key, value = item.split("=", 1)
        try:
            out[key.strip()] = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:  # not a TOML value: taken as a bare string (--set name=ffcc)
            out[key.strip()] = value
    return out


def _named_tables(path, table: str, tables: dict, known, what: str):
    """(name, its table, where) for each ``[TABLE.NAME]`` of ``tables``; one line when a name is not among
    ``known`` or its value is no table."""
    for name, opts in tables.items():
        where = f"[{table}.{name}]"
        if name not in known:
            raise _fail(path, where, f"unknown {what} (known: {', '.join(known)})")
        if not isinstance(opts, dict):
            raise _fail(path, where, "must be a table")
        yield name, opts, where


def _check_strategy_options(path, scenario) -> None:
    """Build each strategy named in [identifier.options.NAME] once, so a bad option fails at load."""
    from identifier import STRATEGIES

    options = dict(scenario.identifier.get("options", {}))
    if PEAK_ESTIMATE in options:
        _check_peak_estimate_options(path, options.pop(PEAK_ESTIMATE), scenario.run.exchange_period_s)
    for name, opts, where in _named_tables(path, "identifier.options", options, STRATEGIES, "strategy"):
        known = strategy_option_keys(STRATEGIES[name])
        for key, value in opts.items():
            if key not in known:
                raise _fail(path, f"{where} {key}", f"unknown option (known: {', '.join(sorted(known))})")
            if key in OPTION_CAPS:
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                        or value != int(value):
                    raise _fail(path, f"{where} {key}", f"must be a whole number, got {value!r}")
                _in_range(path, f"{where} {key}", value, (0, OPTION_CAPS[key]))
        draws = opts.get("particles", 0) * opts.get("noise_block", 0)
        if draws > MAX_NOISE_DRAWS:
            raise _fail(path, where, f"particles x noise_block is {draws:.3g} noise draws held at once; more than "
                        f"{MAX_NOISE_DRAWS:.0e} are refused")
        try:
            STRATEGIES[name](scenario.identifier_settings(), 0)
        except (ValueError, TypeError, ArithmeticError) as e:
            raise _fail(path, where, e) from None


#: ``[identifier.options.peak_estimate]``: the options of the TCU's peak estimate (identifier/peak_estimate.py
#: ``DEFAULTS``), beside the strategies' tables
PEAK_ESTIMATE = "peak_estimate"


def _check_peak_estimate_options(path, opts, period_s: float) -> None:
    """Build the peak estimate once with ``opts``, so a bad option fails at load."""
    from identifier.peak_estimate import DEFAULTS, PeakEstimator

    where = f"[identifier.options.{PEAK_ESTIMATE}]"
    if not isinstance(opts, dict):
        raise _fail(path, where, "must be a table")
    for key, value in opts.items():
        if key not in DEFAULTS:
            raise _fail(path, f"{where} {key}", f"unknown option (known: {', '.join(sorted(DEFAULTS))})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0 \
                and key not in ("prior_mu", "min_creep_kmh"):
            raise _fail(path, f"{where} {key}", f"must be a positive number, got {value!r}")
    try:
        PeakEstimator(period_s, opts, compiled=False)
    except (ValueError, TypeError, ArithmeticError) as e:
        raise _fail(path, where, e) from None


#: the options every strategy takes (the shared evaluation constants)
SHARED_OPTIONS = ("window_samples", "k_pe", "c_lw", "c_up")


def strategy_option_keys(cls) -> set[str]:
    """The keys ``[identifier.options.NAME]`` may hold for strategy class ``cls``: its ``defaults``
    (or ``option_keys``, or its module's ``DEFAULTS``) and ``SHARED_OPTIONS``; a strategy with none of
    them (``nlls``) takes the shared ones only."""
    import sys

    own = getattr(cls, "defaults", None)
    if own is None:
        own = getattr(cls, "option_keys", None)
    if own is None:
        own = getattr(sys.modules[cls.__module__], "DEFAULTS", None)
    return set(own or ()) | set(SHARED_OPTIONS)


def _check_dbc_ranges(path, vehicle, run, sensors) -> None:
    """The speeds at the start, with six standard deviations of sensor noise, must fit the PlantSensor
    frame's ranges (hil/hil.dbc); otherwise the TCU would reject the plant's frames."""
    motor = run.initial_train_speed_ms * vehicle.gear_ratio / vehicle.wheel_radius_m
    for where, value, noise, limit in (
            ("[sensors] motor_speed_noise_rad_s", motor, sensors.motor_speed_noise_rad_s, DBC_MOTOR_SPEED_RAD_S),
            ("[sensors] train_speed_noise_ms", run.initial_train_speed_ms, sensors.train_speed_noise_ms,
             DBC_TRAIN_SPEED_MS)):
        if abs(value) + 6 * noise > limit:
            raise _fail(path, where, f"{noise:g}: six of it around the starting speed {value:.4g} leave the "
                        f"PlantSensor frame's range +-{limit:g} (hil/hil.dbc)")


def load_scenario(path, overrides: dict | None = None) -> Scenario:
    """Load and validate a scenario file; raises ScenarioError with a one-line message."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ScenarioError(f"{path}: no such scenario file") from None
    except IsADirectoryError:
        raise ScenarioError(f"{path}: is a directory, not a scenario file") from None
    except UnicodeDecodeError as e:
        raise ScenarioError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason}); a scenario is a TOML file") from None
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read: {e.strerror or e}") from None
    return parse_scenario(text, str(path), overrides)
