"""The TCU's control laws: a reading, the driver's demand and the identifier's state in, a torque out.

``LAWS`` maps each name (``[control] law``, ``hil run --control``) to its class (identifier/control/laws.py);
``make_controller`` builds one with its options checked; ``check_options`` checks a law's options alone
(the scenario loader calls it, so a bad option fails at load).  The oracle that reads the true curve is
not here: only the benchmark has it (hil/benchmarks/control.py), never a run.
"""
from .base import ControlInput, Controller, CreepLoop
from .laws import ConstantCreep, Demand, ExtremumSeeking, Identified, Readhesion

LAWS = {c.name: c for c in (Demand, Readhesion, ConstantCreep, ExtremumSeeking, Identified)}
DEFAULT_LAW = "demand"


def make_controller(name: str, vehicle, nominal_peak_creep_kmh: float, options: dict | None = None) -> Controller:
    if name not in LAWS:
        raise ValueError(f"unknown control law {name!r} (known: {', '.join(LAWS)})")
    return LAWS[name](vehicle, nominal_peak_creep_kmh, options)


def check_options(name: str, options: dict) -> None:
    """ValueError (one line naming the option) when ``options`` do not suit law ``name``."""
    from ..settings import VehicleModel
    make_controller(name, VehicleModel(1.0, 1.0, 1.0, 1.0), 1.0, options)


__all__ = ["ControlInput", "Controller", "CreepLoop", "LAWS", "DEFAULT_LAW", "make_controller", "check_options"]
