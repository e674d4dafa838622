"""``hil replay LOG``: re-run the identifier offline on a recorded run (MCAP, or a CAN log with --scenario)."""
from __future__ import annotations

import json
import sys

from identifier import STRATEGIES

from ..errors import ConfigError
from .run import print_summary


def register(sub) -> None:
    p = sub.add_parser("replay", help="re-identify a recorded run offline (MCAP log or candump/asc/blf CAN log)")
    p.add_argument("log", help="MCAP log of 'hil run', or a CAN log python-can reads (.log candump, .asc, .blf)")
    p.add_argument("--strategy", default=None, help="identification strategy (default: the logged run's; "
                   f"available: {', '.join(sorted(STRATEGIES))})")
    p.add_argument("--seed", type=int, default=None, help="identifier seed (default: the logged run's)")
    p.add_argument("--scenario", default=None, help="scenario TOML (default: the one stored in the MCAP log; "
                   "required for CAN logs)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.set_defaults(func=cmd_replay)


def cmd_replay(args) -> int:
    if args.strategy is not None and args.strategy not in STRATEGIES:
        raise ConfigError(f"unknown strategy {args.strategy!r}; available: {', '.join(sorted(STRATEGIES))}")
    from ..replay import damage_warning, load_source, replay

    src = load_source(args.log, args.scenario)
    warning = damage_warning(src)
    if warning:
        print(f"hil replay: {warning}", file=sys.stderr)
    summary = replay(src, args.strategy, args.seed)
    if summary.get("counterfactual"):
        print(f"hil replay: counterfactual: the log is a closed-loop run (control law {summary['control']}) whose "
              f"torques came from strategy {summary['logged']['strategy']}; strategy {summary['strategy']} would "
              "have commanded others, so the readings replayed here are not the ones it would have met",
              file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
        return 0
    print_replay(summary)
    m = summary["matches_log"]
    lg = summary["logged"]
    verdict = {True: "matches the logged identification", False: "DIFFERS from the logged identification",
               None: "not comparable with the log"}[m]
    print(f"  replay ({summary['source']}): {summary['messages_read']} messages read, {summary['sensor_readings']} "
          f"sensor readings in {summary['wall_s']:.3f} s = {summary['samples_per_s']:.0f} samples/s; {verdict} "
          f"(logged: {lg['strategy'] or 'result frames'}{'' if lg['seed'] is None else ' seed %d' % lg['seed']}, "
          f"{lg['corrections']} corrections)")
    return 0


def print_replay(s: dict, file=sys.stdout) -> None:
    """``hil run``'s summary lines under a replay heading."""
    print_summary({**s, "mcap": None}, file=file,
                  heading=f"replay {s['mcap']}: scenario {s['scenario']}  strategy {s['strategy']}  seed {s['seed']}")
