"""``hil gap REAL_LOG --model SCENARIO``: diagnose the sim-to-real gap of a recorded run."""
from __future__ import annotations

import json

from ..errors import ConfigError
from ..config import load_scenario


def register(sub) -> None:
    p = sub.add_parser("gap", help="sim-to-real gap: where it lies, which effect explains it, how far it shrinks")
    p.add_argument("real_log", help="log of the real run: MCAP (hil run) or a CAN log python-can reads (.log candump, .asc, .blf, ...)")
    p.add_argument("--model", required=True, help="scenario TOML of the nominal model, e.g. scenarios/ffcc_a.toml")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--report", metavar="DIR", help="write report.md, PNG plots and gap.json into DIR")
    p.add_argument("--block", type=int, default=20, help="periods per fit/held-out block (default 20)")
    p.add_argument("--max-creep-kmh", type=float, default=8.0,
                   help="analyse until the measured creep first exceeds this (default 8 km/h)")
    p.add_argument("--no-identify", action="store_true", help="skip the identification replays")
    p.set_defaults(func=cmd_gap)


def cmd_gap(args) -> int:
    from ..gap import diagnose, read_real_log
    from ..terminal import wrap_lines
    from ..gap.report import text_summary, write_report

    if args.block < 2:
        raise ConfigError(f"--block {args.block}: must be >= 2")
    if args.max_creep_kmh <= 0:
        raise ConfigError(f"--max-creep-kmh {args.max_creep_kmh}: must be > 0")
    scenario = load_scenario(args.model)
    if scenario.rail is not None:
        raise ConfigError(f"{args.model}: a model with [[rail]] segments: hil gap does not handle a segmented model "
                          "yet (give it a scenario with [curves.fault])")
    data = read_real_log(args.real_log, scenario.run.exchange_period_s)
    out, result = diagnose(data, scenario, block=args.block, max_creep_kmh=args.max_creep_kmh,
                       identify=not args.no_identify, progress=True)
    if args.report:
        path = write_report(out, result, args.report)
        out["report"] = str(path)
    if args.json:
        print(json.dumps(out))
    else:
        print(wrap_lines(text_summary(out)))      # the report's copy keeps whole lines
        if args.report:
            print(f"  report: {out['report']}")
    return 0
