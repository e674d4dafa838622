"""``hil run SCENARIO``: one HIL run, recorded to MCAP; ``--json`` prints its summary."""
from __future__ import annotations

import json
import sys

from identifier import DEFAULT_STRATEGY, STRATEGIES

from ..config import load_scenario, parse_set
from ..errors import ConfigError


def register(sub) -> None:
    p = sub.add_parser("run", help="run a scenario on the HIL loop and record it to MCAP")
    p.add_argument("scenario", help="scenario TOML file, e.g. scenarios/ffcc_a.toml")
    p.add_argument("--bus", default="auto", help="bus between plant and TCU: auto (socketcan:vcan0 when the kernel "
                   "has it, else local), local (the embedded relay-free bus), hub (python-can-remote on 127.0.0.1), "
                   "socketcan:<ch>, inprocess (no second process, same frames), or any python-can interface:channel "
                   "(default: auto)")
    p.add_argument("--tcu", choices=("process", "external"), default="process",
                   help="process: start the identifier as a second process (default); external: a TCU already on "
                   "the bus answers (hil tcu elsewhere, or a real TCU)")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                   help="lockstep: the plant waits for the TCU's command each period (deterministic); realtime: "
                   "paced by the wall clock, deadline misses and jitter recorded (default: lockstep)")
    p.add_argument("--strategy", default=DEFAULT_STRATEGY,
                   help=f"identification strategy ({', '.join(sorted(STRATEGIES))}; default {DEFAULT_STRATEGY})")
    p.add_argument("--seed", type=int, default=None, help="seed for sensor noise and the identifier "
                   "(default: the scenario's)")
    p.add_argument("--out", default=None, help="directory for the MCAP log (default: logs/)")
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE",
                   help="override a scenario field, e.g. --set run.duration_s=600 (repeatable)")
    p.add_argument("--reality", action="append", metavar="EFFECT[:PARAM=VALUE,...]",
                   help="switch on an effect the nominal model lacks, for a 'real' run (repeatable; "
                   "see hil/effects.py, e.g. load_transfer:bogie_height_m=1.5, can:delay_ms=3)")
    p.add_argument("--plant", default=None, metavar="casadi|fmu:PATH",
                   help="plant model: the CasADi model or an FMI 2.0/3.0 Co-Simulation FMU (default: the "
                   "scenario's [plant] table, else casadi). Loading an FMU runs its native code")
    p.add_argument("--control", default=None, metavar="LAW",
                   help="the TCU's control law (demand, readhesion, constant_creep, extremum_seeking, identified; "
                   "default: the scenario's [control] law, else demand: open loop as the paper ran it)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--no-rrd", action="store_true", help="do not write the Rerun recording (.rrd) beside the log")
    p.set_defaults(func=cmd_run)


def cmd_run(args) -> int:
    if args.strategy not in STRATEGIES:
        raise ConfigError(f"unknown strategy {args.strategy!r}; available: {', '.join(sorted(STRATEGIES))}")
    if args.control is not None:
        from identifier.control import LAWS
        if args.control not in LAWS:
            raise ConfigError(f"--control {args.control!r}: unknown control law (known: {', '.join(LAWS)})")
        args.set = [*(args.set or []), f"control.law={json.dumps(args.control)}"]
    scenario = load_scenario(args.scenario, parse_set(args.set))
    scenario = apply_reality_args(scenario, args.reality)
    from ..errors import PeerSilent
    from ..exchange import check_deadlines, run
    from ..plants import make_plant, plant_label
    from ..log.record import prepare_out_dir
    from ..progress import compile_kernels

    plant = make_plant(scenario, args.plant)   # None: the CasADi model; a refused FMU creates no --out
    try:
        prepare_out_dir(args.out)              # a bad --out is told now, not after a first-run compile
    except ConfigError:
        if plant is not None:
            plant.close()
        raise
    if args.tcu != "external":
        compile_kernels("hil run")             # the first run on a machine: shown, not a silent wait
    try:
        summary = run(scenario, args.strategy, args.seed, bus=args.bus, mode=args.mode, out_dir=args.out,
                      set_args=args.set, plant=plant, plant_label=plant_label(plant),
                      external_tcu=args.tcu == "external")
    except PeerSilent as e:
        if args.json and getattr(e, "summary", None) is not None:
            print(json.dumps(e.summary))      # still the one JSON object, with the fault in it
        raise PeerSilent(f"{e}; fault recorded, log closed") from None
    finally:
        if plant is not None:
            plant.close()
    rrd = None if args.no_rrd or not summary.get("mcap") else write_rrd_beside(summary["mcap"])
    if args.json:
        print(json.dumps(summary))
    else:
        print_summary(summary)
        if rrd:
            print(f"  rerun: {rrd}")
    sys.stdout.flush()
    check_deadlines(summary)     # real time: too many misses -> exit 5, after the logs and the summary
    return 0


def write_rrd_beside(mcap_path):
    """The Rerun recording beside the MCAP (hil view); its path on stderr; a failure only warns."""
    from ..view import write_rrd

    try:
        rrd, _ = write_rrd(mcap_path)
    except Exception as e:  # noqa: BLE001 - the run itself succeeded; the .rrd can be made later with hil view
        print(f"hil run: warning: no Rerun recording written ({type(e).__name__}: {e}); try hil view {mcap_path}",
              file=sys.stderr)
        return None
    print(f"hil run: Rerun recording {rrd}", file=sys.stderr)
    return rrd


def apply_reality_args(scenario, items):
    """``--reality EFFECT[:p=v,...]`` merged into the scenario's [reality] table (validated)."""
    from ..effects import parse_effect, with_reality
    try:
        parsed = dict(parse_effect(item) for item in items or [])
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return with_reality(scenario, parsed) if parsed else scenario


def print_summary(s: dict, file=sys.stdout, heading: str | None = None) -> None:
    """The run summary as text (``hil.run_summary``): every line within 100 characters, every figure "n/a"
    where the source lacks it (e.g. a CAN log has no truth)."""
    from ..run_summary import RunSummary

    print(RunSummary.from_json(s).text(heading), file=file)
