"""Choose the loop's plant: the CasADi model (default) or an FMU, from ``--plant`` or a ``[plant]`` table.

    --plant casadi              the CasADi WheelsetPlant (default)
    --plant fmu:PATH            an FMI 2.0/3.0 Co-Simulation FMU through fmpy (plant.fmu_plant.FmuPlant)

Scenario table (all keys optional; ``--plant`` overrides ``fmu``):

    [plant]
    fmu = "wheelset.fmu"            # relative to the scenario file's folder
    [plant.mapping]                 # role -> FMU variable (roles: plant.fmu_plant.ROLES)
    torque_nm = "f"
    motor_speed_rad_s = "mass.v"
    train_speed_ms = "y"
    [plant.parameters]              # FMU parameter -> value, set before initialisation
    "damper.d" = 20.0
"""
from __future__ import annotations

from pathlib import Path

from .config import PLANT_KEYS
from .errors import ConfigError, PlantError

__all__ = ["PLANT_KEYS", "make_plant", "parse_plant_spec", "plant_label"]


def parse_plant_spec(spec: str | None) -> tuple[str, str | None]:
    """'casadi' -> ('casadi', None); 'fmu:PATH' -> ('fmu', PATH); None -> ('', None) (= from the scenario)."""
    if spec is None or spec == "":
        return "", None
    if spec == "casadi":
        return "casadi", None
    if spec.startswith("fmu:") and len(spec) > 4:
        return "fmu", spec[4:]
    raise ConfigError(f"--plant {spec!r}: expected 'casadi' or 'fmu:PATH'")


def make_plant(scenario, spec: str | None = None):
    """The plant for one run: None for the built-in CasADi model (the loop builds it, with any
    ``[reality]`` plant effects), else an ``FmuPlant`` (call ``close()`` when done).

    ``spec``: the ``--plant`` value or None to follow the scenario's ``[plant]`` table.
    """
    kind, path = parse_plant_spec(spec)
    table = scenario.extra.get("plant", {})      # its shape was checked when the scenario was loaded
    if kind == "casadi" or (kind == "" and "fmu" not in table):
        return None
    reality_plant_effects = _reality_plant_effects(scenario)
    if reality_plant_effects:
        raise ConfigError(f"{scenario.path}: [reality] plant effects ({', '.join(reality_plant_effects)}) run on the "
                        "CasADi model and cannot be combined with an FMU plant; drop them or use --plant casadi")
    if path is None:
        p = Path(table["fmu"]).expanduser()
        path = p if p.is_absolute() else Path(scenario.path).parent / p
    from plant.fmu_plant import FmuError, FmuPlant

    try:
        return FmuPlant(path, scenario.plant_config(), mapping=table.get("mapping"),
                        parameters=table.get("parameters"))
    except FmuError as e:
        raise PlantError(str(e)) from None


def _reality_plant_effects(scenario) -> list[str]:
    from plant.reality import PLANT_ORDER

    return [name for name in (scenario.extra.get("reality") or {}) if name in PLANT_ORDER]


def plant_label(plant) -> str | None:
    """The plant's name in log names and summaries: None for the CasADi model, ``fmu-<file stem>``."""
    if plant is None:
        return None
    return f"fmu-{Path(str(getattr(plant, 'path', 'plant'))).stem}"
