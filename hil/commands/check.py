"""``hil check LOG CHECKS.toml``: judge a recorded run by a checks file; exit 0 pass, 1 fail, the error
tree's codes for a log it cannot judge (``hil.checks.offline``)."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("check", help="judge a recorded run (MCAP or CAN log) by a checks file: pass (0) or fail (1)")
    p.add_argument("log", help="MCAP log of 'hil run', or a rig's CAN log (.asc, .blf, .log, .csv, .trc, .mf4)")
    p.add_argument("checks", help="checks file: TOML with [[check]] tables (docs: reference/checks)")
    p.add_argument("--junitxml", metavar="FILE", default=None,
                   help="write JUnit XML here, with a figure per failed check in FILE's stem + '-figures/'")
    p.add_argument("--dbc", metavar="FILE", default=None, help="the DBC a CAN log's frames are decoded with "
                   "(default: hil/hil.dbc)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the failed checks")
    p.set_defaults(func=cmd_check)


def cmd_check(args) -> int:
    from ..errors import BenchError
    from ..checks.offline import check_log

    j = check_log(args.log, args.checks, args.junitxml, args.dbc)
    if isinstance(j.verdict, BenchError):
        if args.junitxml:
            print(f"junit: {args.junitxml}", file=sys.stderr)
        raise j.verdict
    if j.verdict is not None:
        print(f"FAIL run: {j.verdict}")
    for r in j.results:
        if not (args.quiet and r.passed):
            print(("PASS " if r.passed else "FAIL ") + r.line())
        if id(r) in j.figures:
            print(f"  figure: {j.figures[id(r)]}")
    failed = sum(1 for r in j.results if not r.passed)
    print(f"{len(j.results) - failed} of {len(j.results)} checks passed"
          + (f"; junit: {args.junitxml}" if args.junitxml else "") + f" ({j.seconds:.2f} s to judge)")
    return 0 if j.passed else 1
