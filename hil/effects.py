"""Every effect a "real" run can switch on that the nominal model lacks: the registry, one record per
effect (``EffectSpec``: name, level, parameters with units, defaults and the range a vehicle allows,
its plant equations, whether and how the gap diagnosis fits it, how ``hil bench gap`` draws it; the
plant, ``hil.gap.candidates`` and the bench read it; ``add_effect`` adds one), the
parsing of ``--reality NAME:p=v,...`` and ``[reality]`` tables, and the wiring of a scenario's effects
into a run (``Reality``).

Levels: **plant** effects are physics, integrated by ``plant.reality.RealityPlant``; **sensor** effects
wrap the sensor model (``plant.reality.RealitySensors``); the **bus** effect ``can`` (delay, jitter and
loss of sensor frames) is ``CanReality`` below: frame j is sent at j*T and arrives at
j*T + delay + jitter*U(0,1) unless lost (probability ``loss``); at its period k the TCU uses the
newest frame that has arrived by k*T, re-stamped with its own step k.

The truth (effects and parameters, and realised CAN figures) is written to the log under ONE metadata
key, ``TRUTH_KEY``; the gap diagnosis reads logs only through ``hil.gap.data.read_real_log``, which drops
that key.  ``parse_effect("load_transfer:bogie_height_m=1.5")`` and ``effects_from_table({...})`` give
``{name: {param: value}}`` with defaults filled in; unknown names or parameters raise ``ValueError``
with a one-line message.
"""
from __future__ import annotations

import dataclasses
import heapq
import json
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from identifier import SensorReading
from plant import reality
from plant.reality import RealityPlant, RealitySensors, fill_defaults

from .errors import ConfigError

TRUTH_KEY = "reality_truth"

U = lambda g, a, b: float(g.uniform(a, b))  # noqa: E731
LOGU = lambda g, a, b: float(math.exp(g.uniform(math.log(a), math.log(b))))  # noqa: E731


@dataclass(frozen=True)
class PlantFit:
    """How the diagnosis fits a plant-level effect (``hil.gap.candidates.PlantCandidate``): the
    parameters it fits (the others keep their defaults, scenario values filled in), their search range
    ``lo``-``hi``, fitted in log space where ``log`` (positive scale parameters), and the coarse scan's
    points per parameter before the local fit (so it starts in the right basin)."""

    params: tuple
    lo: tuple
    hi: tuple
    log: tuple
    scan: tuple = (9,)


@dataclass(frozen=True)
class DelayFit:
    """How the diagnosis fits a sensor form that reports the plant late
    (``hil.gap.candidates.SensorDelayCandidate``): ``form`` "pure", "low_pass" or "per_signal", its one
    parameter (ms) searched over 0-``max_periods`` exchange periods."""

    form: str
    param: str
    max_periods: float = 20.0


@dataclass(frozen=True)
class Draw:
    """One way ``hil bench gap`` draws the effect: the case ``kind`` (``library_form`` the candidates'
    own form, ``held_out_form`` a form the candidate list does not use, ``rail``, ``outside`` no
    candidate's class, ``out_of_library`` the family member ``member`` classed ``member_class``
    before any diagnosis: "outside", "nuisance", or "library", a library class in a form its candidate
    was not written from, whose right answer names that class), ``sample(rng) -> params``, the
    parameter a library form's fit must recover (``recover``) and, for the two-effect cases, the
    effect's place in the list they draw from (``pair_rank``; 0: not drawn in pairs)."""

    kind: str
    sample: Callable
    recover: str = ""
    member: str = ""
    member_class: str = ""
    pair_rank: int = 0


@dataclass(frozen=True)
class EffectSpec:
    """Everything about one effect, in one place: its name, level, parameters (defaults, units, the
    range a vehicle allows: ``plausible``, param -> (lo, hi), what the diagnosis holds a fit to), its
    equations (plant level: ``plant.reality.Equations``, registered with the plant by ``add_effect``),
    whether and how the diagnosis fits it (``candidate``, ``fit``: ``PlantFit``, ``DelayFit``, or the
    fitter's own kind "quantiser" / "frames"), the class it is a form of and the form's name, and how
    the bench draws it (``draws``)."""

    name: str
    level: str                         # "plant" | "sensor" | "bus"
    params: dict                       # param -> default value
    doc: str
    units: dict = field(default_factory=dict)
    candidate: bool = True             # offered to the diagnosis as an explanation
    cls: str = ""                      # the effect class it is a form of ("" = its own name)
    form: str = ""                     # the form's name within its class
    fit: object = None                 # PlantFit | DelayFit | "quantiser" | "frames" | None
    draws: tuple = ()
    plausible: dict = field(default_factory=dict)
    equations: object = None           # plant level: plant.reality.Equations (default: the plant's own)

    def __post_init__(self):
        if self.level == "plant" and self.equations is None and self.name in reality.EQUATIONS:
            object.__setattr__(self, "equations", reality.EQUATIONS[self.name])

    @property
    def effect_class(self) -> str:
        return self.cls or self.name

    def draw(self, kind: str) -> Draw | None:
        return next((d for d in self.draws if d.kind == kind), None)


_GEOMETRY = {"half_bogie_distance_m": None, "half_wheelbase_m": None, "coupler_height_m": None, "bogie_height_m": None}
#: the height z of the bogie's traction pivot a vehicle allows (m; Table 1's is 2.6 m, the bench draws 0.5-2.6 m):
#: a fit that needs a few centimetres stands for another change of the curve's shape at low creep, not an axle
#: load transfer (issue 51: fitted 0.06-0.32 m on such a case), and weighs against its candidate
_BOGIE_HEIGHT = {"bogie_height_m": (0.4, 4.0)}

EFFECTS: dict[str, EffectSpec] = {}


def _quantiser_under_noise(g) -> dict:
    """The motor encoder's quantum as the library form draws it, and noise q/60-q/30 added after it."""
    q = LOGU(g, 0.04, 0.2)
    return {"motor_quantum_rad_s": q, "motor_noise_after_rad_s": q / U(g, 30.0, 60.0)}


def add_effect(spec: EffectSpec) -> EffectSpec:
    """Register an effect: its record here and, at plant level, its equations with the plant
    (``plant.reality.add_equations``); the plant, the candidate list (``hil.gap.candidates``) and the
    bench (``hil.benchmarks.gap``) read it from here."""
    if spec.name in EFFECTS:
        raise ValueError(f"effect {spec.name!r} is already registered")
    if spec.level not in ("plant", "sensor", "bus"):
        raise ValueError(f"effect {spec.name!r}: level must be plant, sensor or bus, got {spec.level!r}")
    if spec.level == "plant":
        if spec.equations is None:
            raise ValueError(f"plant effect {spec.name!r}: give its equations (plant.reality.Equations)")
        reality.add_equations(spec.name, spec.equations)
    if spec.candidate and spec.fit is None:
        raise ValueError(f"effect {spec.name!r} is a candidate: give its fit settings")
    EFFECTS[spec.name] = spec
    return spec


def remove_effect(name: str) -> None:
    """Unregister an effect ``add_effect`` added (its record and its plant equations): for a test or an
    experiment that adds one and must leave the registry as it found it."""
    spec = EFFECTS.pop(name)
    if spec.level == "plant":
        reality.EQUATIONS.pop(name, None)


for _spec in [
    EffectSpec("load_transfer", "plant", dict(_GEOMETRY),
               "axle load transfer under traction (L, L_b, Z, z; defaults from the scenario's [vehicle])",
               {"half_bogie_distance_m": "m", "half_wheelbase_m": "m", "coupler_height_m": "m", "bogie_height_m": "m"},
               form="static", fit=PlantFit(("bogie_height_m",), (0.0,), (6.0,), (False,)),
               draws=(Draw("library_form", lambda g: {"bogie_height_m": U(g, 0.5, 2.6)}, recover="bogie_height_m",
                           pair_rank=1),),
               plausible=_BOGIE_HEIGHT),
    EffectSpec("load_transfer_pitch", "plant", dict(_GEOMETRY, pitch_hz=4.0, pitch_damping=0.2),
               "axle load transfer reached through a bogie pitch mode (second order, pitch_hz, pitch_damping)",
               {"bogie_height_m": "m", "pitch_hz": "Hz", "pitch_damping": "-"},
               cls="load_transfer", form="pitch_mode",
               fit=PlantFit(("bogie_height_m", "pitch_hz"), (0.0, 0.5), (6.0, 20.0), (False, True), (7, 5)),
               draws=(Draw("held_out_form", lambda g: {"bogie_height_m": U(g, 0.5, 2.6), "pitch_hz": U(g, 2.0, 8.0),
                                                       "pitch_damping": U(g, 0.1, 0.4)}, pair_rank=7),),
               plausible=_BOGIE_HEIGHT),
    EffectSpec("torque_lag", "plant", {"tau_s": 0.005}, "first-order motor/inverter torque lag",
               {"tau_s": "s"}, form="first_order", fit=PlantFit(("tau_s",), (2e-4,), (0.1,), (True,))),
    EffectSpec("compliance", "plant",
               {"stiffness_nm_rad": 3e5, "damping_ratio": 0.05, "backlash_rad": 0.0},
               "drivetrain torsional compliance (motor side) with gear backlash (half-width)",
               {"stiffness_nm_rad": "N·m/rad", "damping_ratio": "-", "backlash_rad": "rad"},
               form="stiffness_backlash",
               # the ring frequency makes the stiffness cost multimodal: a fine scan in stiffness
               fit=PlantFit(("stiffness_nm_rad", "damping_ratio"), (2e4, 0.005), (5e6, 1.0), (True, True), (17, 4)),
               draws=(Draw("library_form", lambda g: {"stiffness_nm_rad": LOGU(g, 1e5, 1e6),
                                                      "damping_ratio": U(g, 0.02, 0.15),
                                                      "backlash_rad": U(g, 0.0, 0.002)},
                           recover="stiffness_nm_rad", pair_rank=2),)),
    EffectSpec("drivetrain_damping", "plant", {"viscous_nm_s_rad": 5.0, "coulomb_nm": 50.0},
               "drivetrain losses: viscous (x motor speed) and Coulomb torque taken off the motor torque",
               {"viscous_nm_s_rad": "N·m·s/rad", "coulomb_nm": "N·m"}, cls="compliance",
               form="viscous_coulomb",
               fit=PlantFit(("viscous_nm_s_rad", "coulomb_nm"), (0.0, 0.0), (20.0, 400.0), (False, False), (5, 5)),
               draws=(Draw("held_out_form", lambda g: {"viscous_nm_s_rad": U(g, 0.2, 2.0),
                                                       "coulomb_nm": U(g, 5.0, 40.0)}),)),
    EffectSpec("gear_efficiency", "plant", {"efficiency": 0.97},
               "drivetrain losses as a gear efficiency: the torque reaching the wheelset is efficiency x the "
               "motor's", {"efficiency": "-"}, cls="compliance", form="efficiency",
               fit=PlantFit(("efficiency",), (0.5,), (1.0,), (False,), (11,)),
               draws=(Draw("held_out_form", lambda g: {"efficiency": U(g, 0.93, 0.99)}),)),
    EffectSpec("adhesion_lag", "plant", {"tau_s": 0.01}, "adhesion dynamics: mu relaxes to the curve with tau_s",
               {"tau_s": "s"}, form="mu_lag", fit=PlantFit(("tau_s",), (2e-4,), (0.2,), (True,)),
               draws=(Draw("library_form", lambda g: {"tau_s": LOGU(g, 0.003, 0.03)}, recover="tau_s",
                           pair_rank=3),)),
    EffectSpec("creep_relaxation", "plant", {"relaxation_length_m": 0.3},
               "adhesion dynamics: mu relaxes to the curve over a rolled length (tau = L / v_train)",
               {"relaxation_length_m": "m"}, cls="adhesion_lag", form="creep_relaxation",
               fit=PlantFit(("relaxation_length_m",), (2e-3,), (10.0,), (True,)),
               draws=(Draw("held_out_form", lambda g: {"relaxation_length_m": LOGU(g, 0.05, 0.8)}, pair_rank=5),)),
    EffectSpec("bristle", "plant", {"stiffness_per_m": 200.0, "damping_s_per_m": 0.0},
               "adhesion dynamics, LuGre-type bristle: z' = w - |w| z / g(v_s), mu = s0 z + s1 z'",
               {"stiffness_per_m": "1/m", "damping_s_per_m": "s/m"}, cls="adhesion_lag",
               form="bristle",
               fit=PlantFit(("stiffness_per_m", "damping_s_per_m"), (5.0, 0.0), (1e4, 0.05), (True, False), (9, 3)),
               draws=(Draw("held_out_form", lambda g: {"stiffness_per_m": LOGU(g, 50.0, 400.0),
                                                       "damping_s_per_m": U(g, 0.0, 0.02)}, pair_rank=6),)),
    EffectSpec("adhesion_lag2", "plant", {"natural_hz": 20.0, "damping_ratio": 0.7},
               "adhesion dynamics as a second-order contact lag: mu'' = w^2 (mu_curve - mu) - 2 zeta w mu', "
               "w = 2 pi natural_hz", {"natural_hz": "Hz", "damping_ratio": "-"}, cls="adhesion_lag",
               form="second_order",
               fit=PlantFit(("natural_hz", "damping_ratio"), (1.0, 0.2), (500.0, 3.0), (True, True), (9, 3)),
               # the band of the first-order lag's draws (tau 3-30 ms ~ 2 zeta / w: 5-40 Hz at zeta 0.5-1)
               draws=(Draw("library_form", lambda g: {"natural_hz": LOGU(g, 8.0, 40.0),
                                                      "damping_ratio": U(g, 0.5, 1.0)}, recover="natural_hz"),)),
    EffectSpec("resistance", "plant", {"factor": 1.5}, "running resistance = factor x the Davis polynomial",
               {"factor": "-"}, form="davis_factor", fit=PlantFit(("factor",), (0.0,), (5.0,), (False,)),
               draws=(Draw("library_form", lambda g: {"factor": U(g, 0.4, 0.7) if g.random() < 0.5
                                                      else U(g, 1.4, 2.0)}, recover="factor", pair_rank=4),)),
    EffectSpec("rail_curve", "plant", {"peak_mu_scale": 0.98, "creep_scale": 1.0},
               "the rail's fault curve differs from the scenario's: mu = peak_mu_scale * mu_fault(v_s / creep_scale)",
               {"peak_mu_scale": "-", "creep_scale": "-"}, candidate=False, form="scaled_curve",
               # the nuisance fitted before any effect is compared (hil.gap.candidates.RAIL)
               fit=PlantFit(("peak_mu_scale", "creep_scale"), (0.85, 0.85), (1.18, 1.18), (True, True), (17, 7)),
               draws=(Draw("rail", lambda g: {"peak_mu_scale": 1.0 + float(g.choice([-1, 1])) * U(g, 0.01, 0.05),
                                              "creep_scale": 1.0 if g.random() < 0.5 else 1.0 + U(g, -0.05, 0.05)}),
                      # the rail's curve stretched in creep, inside the nuisance's range (0.85-1.18)
                      Draw("out_of_library", lambda g: {"peak_mu_scale": 1.0, "creep_scale": float(
                          g.choice([-1, 1])) * U(g, 0.06, 0.14) + 1.0}, member="rail_stretch",
                           member_class="nuisance"))),
    EffectSpec("rail_shape", "plant", {"low_creep_scale": 0.8, "knee_kmh": 0.5},
               "the rail's fault curve changed in shape at low creep, its peak and tail kept: mu = mu_fault(v_s / k), "
               "k = 1 + (low_creep_scale - 1) exp(-|v_s| / knee_kmh)", {"low_creep_scale": "-", "knee_kmh": "km/h"},
               candidate=False,
               # stretched or squeezed by 15-35 % near zero creep (beyond the nuisance's uniform 0.85-1.18), fading
               # over 0.3-1 km/h (ffcc_a's fault curve peaks at 1.27 km/h): the rail's curve is what differs, in a
               # shape no scaling of the whole curve makes, where a static load transfer at a few centimetres
               # used to stand for it (issue 51)
               draws=(Draw("out_of_library", lambda g: {"low_creep_scale": 1.0 + float(g.choice([-1, 1]))
                                                        * U(g, 0.15, 0.35), "knee_kmh": U(g, 0.3, 1.0)},
                           member="rail_shape", member_class="nuisance"),)),
    EffectSpec("torque_ripple", "plant", {"amplitude": 0.02, "frequency_hz": 60.0, "phase_rad": 0.0},
               "sinusoidal torque ripple (fraction of the torque)",
               {"amplitude": "-", "frequency_hz": "Hz", "phase_rad": "rad"}, candidate=False,
               draws=(Draw("outside", lambda g: {"amplitude": U(g, 0.01, 0.05), "frequency_hz": U(g, 20.0, 150.0),
                                                 "phase_rad": U(g, 0, 2 * math.pi)}),)),
    EffectSpec("power_limit", "plant", {"power_kw": None, "power_ratio": 1.01},
               "constant-power region of the drive: the motor torque capped at power_kw / omega_m (above the base "
               "speed power_kw / torque); power_kw None: power_ratio x the scenario's equilibrium power",
               {"power_kw": "kW", "power_ratio": "-"}, candidate=False,
               # P_max a ratio of the equilibrium power: the cap binds once the motor runs that much above
               # its equilibrium speed (at the fault's creep rise, or earlier as the train accelerates)
               draws=(Draw("out_of_library", lambda g: {"power_ratio": U(g, 1.005, 1.05)}, member="power_limit",
                           member_class="outside"),)),
    EffectSpec("torque_map", "plant", {"droop": 1.0, "omega0_rad_s": None},
               "the drive's torque gain falling with motor speed: T = T_cmd x max(1 - droop (omega_m / omega0 - 1), "
               "0); omega0_rad_s None: the scenario's equilibrium motor speed",
               {"droop": "-", "omega0_rad_s": "rad/s"}, candidate=False,
               # no knee: it acts as the train speeds up, before the fault too; no candidate adds torque
               # below nor takes it off only above the equilibrium speed (the losses and the rail mimic parts)
               draws=(Draw("out_of_library", lambda g: {"droop": U(g, 0.5, 3.0)}, member="torque_map",
                           member_class="outside"),)),
    EffectSpec("wheel_radius", "plant", {"error_percent": 0.2}, "true wheel radius = nominal x (1 + error)",
               {"error_percent": "%"}, candidate=False,
               draws=(Draw("outside", lambda g: {"error_percent": float(g.choice([-1, 1]) * g.uniform(0.05, 0.3))}),)),
    EffectSpec("sensor_delay", "sensor", {"delay_ms": 3.0}, "speed sensors report values delay_ms old",
               {"delay_ms": "ms"}, form="pure_delay", fit=DelayFit("pure", "delay_ms"),
               draws=(Draw("library_form", lambda g: {"delay_ms": U(g, 1.0, 8.0)}, recover="delay_ms",
                           pair_rank=11),)),
    EffectSpec("sensor_lowpass", "sensor", {"tau_ms": 4.0}, "speed sensors low-pass filtered (first order, tau_ms)",
               {"tau_ms": "ms"}, cls="sensor_delay", form="low_pass", fit=DelayFit("low_pass", "tau_ms"),
               draws=(Draw("held_out_form", lambda g: {"tau_ms": U(g, 1.0, 6.0)}, pair_rank=14),)),
    EffectSpec("motor_delay", "sensor", {"delay_ms": 5.0}, "the motor encoder alone reports values delay_ms old",
               {"delay_ms": "ms"}, cls="sensor_delay", form="per_signal", fit=DelayFit("per_signal", "delay_ms"),
               draws=(Draw("held_out_form", lambda g: {"delay_ms": U(g, 2.0, 12.0)}, pair_rank=15),)),
    EffectSpec("tachometer_gain", "sensor", {"error_percent": 1.0},
               "the motor encoder reads speed x (1 + error_percent / 100)", {"error_percent": "%"}, candidate=False,
               draws=(Draw("outside", lambda g: {"error_percent": float(g.choice([-1, 1]) * g.uniform(0.2, 2.0))}),)),
    EffectSpec("sensor_stick", "sensor", {"start_s": 0.55, "hold_ms": 10.0},
               "the motor encoder sticks: from start_s on it repeats its last reading for hold_ms",
               {"start_s": "s", "hold_ms": "ms"}, candidate=False,
               # stuck for 5-30 ms somewhere in 0.2-0.65 s (the fault of ffcc_a is at 0.5 s: before it the
               # speed hardly moves and the stick may leave no gap at all)
               draws=(Draw("out_of_library", lambda g: {"start_s": U(g, 0.2, 0.65), "hold_ms": U(g, 5.0, 30.0)},
                           member="sensor_stick", member_class="outside"),)),
    EffectSpec("sensor_quantisation", "sensor", {"motor_quantum_rad_s": 0.05, "train_quantum_ms": 0.0,
                                                 "motor_noise_after_rad_s": 0.0},
               "speed sensors quantised (on top of their noise; motor_noise_after_rad_s: noise added after the "
               "motor encoder's quantiser)",
               {"motor_quantum_rad_s": "rad/s", "train_quantum_ms": "m/s", "motor_noise_after_rad_s": "rad/s"},
               form="quantiser", fit="quantiser",
               draws=(Draw("library_form", lambda g: {"motor_quantum_rad_s": LOGU(g, 0.04, 0.2)},
                           recover="motor_quantum_rad_s", pair_rank=12),
                      # noise after the quantiser (q/60-q/30), which hid the lattice's smallest steps: a library
                      # effect in a form the lattice detector was not first written for, so named right or wrong
                      Draw("out_of_library", _quantiser_under_noise, member="quantiser_noise",
                           member_class="library"))),
    EffectSpec("can", "bus", {"delay_ms": 2.0, "jitter_ms": 0.0, "loss": 0.0},
               "CAN sensor frames delayed (+ uniform jitter), lost with probability loss; the TCU uses the "
               "newest frame it has", {"delay_ms": "ms", "jitter_ms": "ms", "loss": "-"}, form="frame_delay",
               fit="frames",
               draws=(Draw("library_form", lambda g: {"delay_ms": float(g.integers(1, 7)), "jitter_ms": U(g, 0.0, 1.0),
                                                      "loss": U(g, 0.0, 0.03)}, recover="delay_ms", pair_rank=13),)),
]:
    add_effect(_spec)


def _number(text: str, where: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{where}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{where}: must be finite, got {text!r}")
    return v


def check_effect(name: str, params: dict, where: str = "reality") -> dict:
    """Validated ``params`` of effect ``name`` with defaults filled in (None = from the scenario)."""
    if name not in EFFECTS:
        raise ValueError(f"{where}: unknown effect {name!r} (known: {', '.join(EFFECTS)})")
    spec = EFFECTS[name]
    out = dict(spec.params)
    for k, v in params.items():
        if k not in spec.params:
            raise ValueError(f"{where} {name}: unknown parameter {k!r} (known: {', '.join(spec.params)})")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            v = _number(str(v), f"{where} {name}.{k}")
        if not math.isfinite(v):
            raise ValueError(f"{where} {name}.{k}: must be finite, got {v!r}")
        out[k] = float(v)
    for k, v in out.items():
        if v is not None and v < 0 and k not in ("phase_rad", "error_percent"):
            raise ValueError(f"{where} {name}.{k}: must be >= 0, got {v}")
    for k in ("relaxation_length_m", "stiffness_per_m", "tau_ms", "peak_mu_scale", "creep_scale", "pitch_hz",
              "power_ratio", "natural_hz"):
        if k in out and not out[k] > 0:
            raise ValueError(f"{where} {name}.{k}: must be > 0, got {out[k]}")
    if name in ("torque_lag", "adhesion_lag") and out["tau_s"] <= 0:
        raise ValueError(f"{where} {name}.tau_s: must be > 0, got {out['tau_s']}")
    if name == "compliance" and out["stiffness_nm_rad"] <= 0:
        raise ValueError(f"{where} compliance.stiffness_nm_rad: must be > 0, got {out['stiffness_nm_rad']}")
    if name == "gear_efficiency" and not 0 < out["efficiency"] <= 1:
        raise ValueError(f"{where} gear_efficiency.efficiency: must be in (0, 1], got {out['efficiency']}")
    if name == "power_limit" and out["power_kw"] is not None and not out["power_kw"] > 0:
        raise ValueError(f"{where} power_limit.power_kw: must be > 0, got {out['power_kw']}")
    if name == "torque_map" and out["omega0_rad_s"] is not None and not out["omega0_rad_s"] > 0:
        raise ValueError(f"{where} torque_map.omega0_rad_s: must be > 0, got {out['omega0_rad_s']}")
    if name == "can" and not out["loss"] < 1:
        raise ValueError(f"{where} can.loss: must be < 1, got {out['loss']}")
    return out


def parse_effect(text: str) -> tuple[str, dict]:
    """``"NAME[:p=v,...]"`` -> (name, params with defaults)."""
    name, _, rest = text.partition(":")
    name = name.strip()
    params = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        if "=" not in item:
            raise ValueError(f"--reality {text!r}: expected PARAM=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        params[k.strip()] = _number(v.strip(), f"--reality {name}.{k.strip()}")
    return name, check_effect(name, params, "--reality")


def effects_from_table(table: dict, where: str = "[reality]") -> dict:
    """A scenario's ``[reality]`` table ``{effect: {param: value}}`` -> validated effects."""
    if not isinstance(table, dict):
        raise ValueError(f"{where}: must be a table of effects")
    out = {}
    for name, params in table.items():
        if params is True:
            params = {}
        if not isinstance(params, dict):
            raise ValueError(f"{where} {name}: must be a table of parameters (or true)")
        out[name] = check_effect(name, params, where)
    return out


class CanReality:
    """``deliver(reading) -> reading the TCU uses this period``; call once per period, in order."""

    def __init__(self, delay_ms: float, jitter_ms: float, loss: float, period_s: float, seed: int):
        self.delay_s = delay_ms * 1e-3
        self.jitter_s = jitter_ms * 1e-3
        self.loss = loss
        self.period_s = period_s
        self._rng = np.random.default_rng([seed, 0xCA4])
        self._queue: list[tuple[float, int, SensorReading]] = []   # (arrival time, send step, reading)
        self._newest: SensorReading | None = None
        self.delays_periods: list[int] = []   # realised (TCU step - send step) per period
        self.lost = 0

    def deliver(self, reading: SensorReading) -> SensorReading:
        k = reading.step
        t_now = k * self.period_s
        if self._newest is None:
            self._newest = reading               # the TCU starts with the initial value
        if self._rng.random() < self.loss:
            self.lost += 1
        else:
            arrival = t_now + self.delay_s + self.jitter_s * self._rng.random()
            heapq.heappush(self._queue, (arrival, k, reading))
        while self._queue and self._queue[0][0] <= t_now + 1e-9:
            _, j, r = heapq.heappop(self._queue)
            if r.step >= self._newest.step:
                self._newest = r
        self.delays_periods.append(k - self._newest.step)
        return SensorReading(k, self._newest.motor_speed_rad_s, self._newest.train_speed_ms)

    def realised(self) -> dict:
        d = np.asarray(self.delays_periods, float)
        return {"mean_delay_ms": float(d.mean() * self.period_s * 1e3) if d.size else 0.0,
                "lost_frames": self.lost, "frames": len(self.delays_periods)}


class Reality:
    """What a scenario's ``[reality]`` table asks for, ready to plug into the loop."""

    def __init__(self, scenario, seed: int):
        raw = scenario.extra.get("reality") or {}
        try:
            effects = effects_from_table(raw, f"{scenario.path}: [reality]")
        except ValueError as e:
            raise ConfigError(str(e)) from None
        cfg = scenario.plant_config()
        self.effects = fill_defaults(effects, cfg)
        self.active = bool(self.effects)
        self.plant = RealityPlant(cfg, self.effects) \
            if any(EFFECTS[n].level == "plant" for n in self.effects) else None
        self.can = None
        if "can" in self.effects:
            c = self.effects["can"]
            self.can = CanReality(c["delay_ms"], c["jitter_ms"], c["loss"], scenario.run.exchange_period_s, seed)
        self._sensor_effects = {n: p for n, p in self.effects.items() if EFFECTS[n].level == "sensor"}
        self.period_s = scenario.run.exchange_period_s

    def wrap_sensors(self, sensors):
        return RealitySensors(sensors, self._sensor_effects, self.period_s) if self._sensor_effects else sensors

    def deliver(self, reading: SensorReading) -> SensorReading:
        return self.can.deliver(reading) if self.can else reading

    def truth(self) -> dict:
        out = {"effects": json.dumps(self.effects)}
        if self.can:
            out["can_realised"] = json.dumps(self.can.realised())
        return out

    def record_truth(self, recorder) -> None:
        """Write the truth under TRUTH_KEY (call at the end of the run: it holds realised figures)."""
        if recorder is not None and self.active:
            recorder.metadata(TRUTH_KEY, self.truth())


def with_reality(scenario, effects: dict):
    """The scenario with ``effects`` ({name: params}) merged into its ``[reality]`` table."""
    table = dict(scenario.extra.get("reality") or {})
    table.update({k: {p: v for p, v in params.items() if v is not None} for k, params in effects.items()})
    return dataclasses.replace(scenario, extra={**scenario.extra, "reality": table})
