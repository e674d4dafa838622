"""``hil replay LOG``: re-run the identifier offline on a recorded run (MCAP, or a CAN log with --scenario)."""
from __future__ import annotations

import json
import sys

from identifier import STRATEGIES

from ..cli import UserError


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
        raise UserError(f"unknown strategy {args.strategy!r}; available: {', '.join(sorted(STRATEGIES))}")
    from ..replay import damage_warning, load_source, replay

    src = load_source(args.log, args.scenario)
    warning = damage_warning(src)
    if warning:
        print(f"hil replay: {warning}", file=sys.stderr)
    summary = replay(src, args.strategy, args.seed)
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


def _f(x, spec):
    return "n/a" if x is None else format(x, spec)


def print_replay(s: dict, file=sys.stdout) -> None:
    """The ``hil run`` summary lines (n/a where a source lacks the truth, e.g. a CAN log has no plant state)."""
    print(f"replay {s['mcap']}: scenario {s['scenario']}  strategy {s['strategy']}  seed {s['seed']}", file=file)
    print(f"  fault at {_f(s['t_fault_s'], '.3f')} s, serious stage at {_f(s['t_serious_s'], '.3f')} s "
          f"(T_det {_f(s['t_det_s'] and s['t_det_s'] * 1e3, '.1f')} ms), slip detected at "
          f"{_f(s['t_detected_s'], '.3f')} s", file=file)
    if s["identified"]:
        print(f"  identified at {_f(s['t_identified_s'], '.3f')} s: RT {_f(s['rt_percent'], '.1f')} % after "
              f"{s['corrections']} corrections", file=file)
    else:
        print(f"  NOT identified ({s['corrections']} corrections)", file=file)
    if s.get("params"):
        print("  params (l0, l1, l2, t1, t2): " + ", ".join(f"{x:.5g}" for x in s["params"]), file=file)
        print(f"  fit: RMSE {_f(s['rmse'], '.3e')}  R2 {_f(s['r2'], '.5f')}; vs true curve: peak mu error "
              f"{_f(s['peak_mu_err_percent'], '.2f')} %, peak creep error {_f(s['peak_creep_err_percent'], '.2f')} %",
              file=file)
