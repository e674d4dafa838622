"""``hil fmu export SCENARIO -o plant.fmu`` and ``hil fmu info PLANT.fmu``: the plant as an FMU."""
from __future__ import annotations

import json
import sys

from ..errors import ConfigError, PlantError


def register(sub) -> None:
    p = sub.add_parser("fmu", help="export the plant as an FMI 2.0 Co-Simulation FMU; inspect an FMU")
    fsub = p.add_subparsers(dest="fmu_command", metavar="ACTION")
    fsub.required = True

    e = fsub.add_parser("export", help="the scenario's plant as an FMI 2.0 (or 3.0) Co-Simulation FMU (needs gcc)")
    e.add_argument("scenario", help="scenario TOML whose values become the FMU's parameter start values")
    e.add_argument("-o", "--output", required=True, help="FMU file to write, e.g. plant.fmu")
    e.add_argument("--terms", type=int, default=None,
                   help="exponential terms per friction curve the FMU holds (default: the scenario's)")
    e.add_argument("--fmi", choices=("2", "3"), default="2", help="FMI version: 2 (2.0, default) or 3 (3.0)")
    e.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE", help="override a scenario field")
    e.set_defaults(func=cmd_export)

    i = fsub.add_parser("info", help="an FMU's type, platforms, variables and fmpy.validation result")
    i.add_argument("fmu", help="FMU file")
    i.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    i.set_defaults(func=cmd_info)


def cmd_export(args) -> int:
    from plant.fmu import FmuExportError, export_fmu

    from ..config import load_scenario
    from ..config import parse_set

    if args.terms is not None and args.terms < 1:
        raise ConfigError(f"--terms {args.terms}: must be >= 1")
    scenario = load_scenario(args.scenario, parse_set(args.set))
    if scenario.rail is not None or scenario.control.demand is not None:
        raise ConfigError(f"{args.scenario}: [[rail]] segments and a [control] demand profile are not exported to an "
                          "FMU yet (its parameters are one normal and one fault curve)")
    try:
        path = export_fmu(scenario.plant_config(), args.output, n_terms=args.terms,
                          description=f"railway-hil wheelset-rail plant, start values from {scenario.name}",
                          stop_time_s=scenario.run.duration_s, fmi_version=args.fmi)
    except (FmuExportError, OSError) as e:
        raise ConfigError(f"{args.output}: {e}") from None
    print(f"wrote {path} (FMI {args.fmi}.0 Co-Simulation, parameters from {args.scenario})", file=sys.stderr)
    return 0


def cmd_info(args) -> int:
    import fmpy
    from fmpy.validation import validate_fmu

    from plant.fmu_plant import FmuError, archive_problems, describe_variables, read_model_description

    try:
        md = read_model_description(args.fmu)
        refused = archive_problems(args.fmu, md)
    except FmuError as e:
        raise PlantError(str(e)) from None
    problems = validate_fmu(args.fmu)
    info = {"fmu": args.fmu, "fmi_version": md.fmiVersion, "model_name": md.modelName,
            "generation_tool": md.generationTool,
            "kinds": [k for k, v in (("CoSimulation", md.coSimulation), ("ModelExchange", md.modelExchange)) if v],
            "platforms": fmpy.supported_platforms(args.fmu), "variables": describe_variables(md),
            "safety_problems": refused, "validation_problems": problems}
    if args.json:
        print(json.dumps(info))
        return 0
    print(f"{args.fmu}: FMI {md.fmiVersion} {' + '.join(info['kinds'])}, model {md.modelName!r} "
          f"by {md.generationTool!r}, platforms {', '.join(info['platforms'])}")
    print(f"  {info['variables']}")
    print("  safety: " + ("no problems (loading it still runs its code: only load FMUs you trust)" if not refused
                          else f"{len(refused)} problem(s); hil refuses to unpack or load this FMU"))
    for p in refused:
        print("    " + p)
    print("  fmpy.validation: " + ("no problems" if not problems else f"{len(problems)} problem(s)"))
    for p in problems:
        print("    " + str(p).replace("\n", "\n    "))
    return 0
