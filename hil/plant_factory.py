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

from .cli import UserError
from .scenario import ScenarioError

PLANT_KEYS = ("fmu", "mapping", "parameters")


def plant_table(scenario) -> dict:
    """The scenario's ``[plant]`` table, checked; ScenarioError naming the field otherwise."""
    table = scenario.extra.get("plant", {})
    path = scenario.path
    if not isinstance(table, dict):
        raise ScenarioError(f"{path}: [plant]: must be a table")
    for key, value in table.items():
        if key not in PLANT_KEYS:
            raise ScenarioError(f"{path}: [plant] {key}: unknown key (known: {', '.join(PLANT_KEYS)})")
    if "fmu" in table and not isinstance(table["fmu"], str):
        raise ScenarioError(f"{path}: [plant] fmu: must be a path string, got {table['fmu']!r}")
    for key in ("mapping", "parameters"):
        if key in table and not isinstance(table[key], dict):
            raise ScenarioError(f"{path}: [plant.{key}]: must be a table, got {table[key]!r}")
    for role, name in table.get("mapping", {}).items():
        if not isinstance(name, str):
            raise ScenarioError(f"{path}: [plant.mapping] {role}: must be an FMU variable name, got {name!r}")
    for name, value in table.get("parameters", {}).items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ScenarioError(f"{path}: [plant.parameters] {name}: must be a number, got {value!r}")
    return table


def parse_plant_spec(spec: str | None) -> tuple[str, str | None]:
    """'casadi' -> ('casadi', None); 'fmu:PATH' -> ('fmu', PATH); None -> ('', None) (= from the scenario)."""
    if spec is None or spec == "":
        return "", None
    if spec == "casadi":
        return "casadi", None
    if spec.startswith("fmu:") and len(spec) > 4:
        return "fmu", spec[4:]
    raise UserError(f"--plant {spec!r}: expected 'casadi' or 'fmu:PATH'")


def make_plant(scenario, spec: str | None = None):
    """The plant for one run: None for the built-in CasADi model (the loop builds it, with any
    ``[reality]`` plant effects), else an ``FmuPlant`` (call ``close()`` when done).

    ``spec``: the ``--plant`` value or None to follow the scenario's ``[plant]`` table.
    """
    kind, path = parse_plant_spec(spec)
    table = plant_table(scenario)
    if kind == "casadi" or (kind == "" and "fmu" not in table):
        return None
    reality_plant_effects = _reality_plant_effects(scenario)
    if reality_plant_effects:
        raise UserError(f"{scenario.path}: [reality] plant effects ({', '.join(reality_plant_effects)}) run on the "
                        "CasADi model and cannot be combined with an FMU plant; drop them or use --plant casadi")
    if path is None:
        p = Path(table["fmu"]).expanduser()
        path = p if p.is_absolute() else Path(scenario.path).parent / p
    from plant.fmu_plant import FmuError, FmuPlant

    try:
        return FmuPlant(path, scenario.plant_config(), mapping=table.get("mapping"),
                        parameters=table.get("parameters"))
    except FmuError as e:
        raise UserError(str(e)) from None


def _reality_plant_effects(scenario) -> list[str]:
    table = scenario.extra.get("reality") or {}
    if not table:
        return []
    try:
        from plant.reality import EFFECTS, effects_from_table
    except ImportError:
        return []
    try:
        effects = effects_from_table(table, f"{scenario.path}: [reality]")
    except ValueError as e:
        raise UserError(str(e)) from None
    return [name for name in effects if EFFECTS[name].level == "plant"]
