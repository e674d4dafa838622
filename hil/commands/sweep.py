"""``hil sweep SWEEP.toml``: a parameter study, each point one run, on Dask (``hil/sweep/``)."""
from __future__ import annotations

import json


def register(sub) -> None:
    p = sub.add_parser("sweep", help="a parameter study: grids and seeded draws over scenario fields, families, "
                       "effects, strategies and seeds, one run per point, on a local or remote Dask cluster")
    p.add_argument("sweep", help="sweep file (TOML), e.g. scenarios/sweeps/mu_noise.toml")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local cluster on "
                   "127.0.0.1, started and stopped here)")
    p.add_argument("--workers", type=int, default=None,
                   help="local cluster: worker processes (default: one per core); 0: no Dask, every point in "
                   "this process; with --scheduler: wait for this many workers")
    p.add_argument("--out", default=None, help="output directory: table/ (Parquet), summary.md, PNG plots "
                   "(default logs/sweep-<name>)")
    p.add_argument("--resume", action="store_true", help="skip the points already in --out's table")
    p.add_argument("--keep-logs", action="store_true", help="write each point's MCAP log under OUT/logs/ "
                   "(on the worker's machine)")
    p.add_argument("--dashboard", action="store_true", help="local cluster: serve Dask's dashboard on "
                   "127.0.0.1:8787 (needs bokeh)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.set_defaults(func=cmd_sweep)


def cmd_sweep(args) -> int:
    from ..sweep.driver import run_sweep
    from ..sweep.spec import load_sweep

    sweep = load_sweep(args.sweep)          # every axis checked before anything runs
    doc = run_sweep(sweep, args.out, scheduler=args.scheduler, workers=args.workers, resume=args.resume,
                    keep_logs=args.keep_logs, dashboard=args.dashboard)
    if args.json:
        print(json.dumps(doc))
    else:
        print(f"sweep {doc['sweep']}: {doc['points']} points, {doc['ran_now']} run now, {doc['skipped']} from the "
              f"table, {doc['failed']} failed, in {doc['wall_s']:.1f} s on {doc['engine'] or 'nothing'}")
        print(f"  table:   {doc['table']}  (pandas.read_parquet)")
        print(f"  summary: {doc['summary']}")
        for p in doc["plots"]:
            print(f"  plot:    {p}")
    return 0
