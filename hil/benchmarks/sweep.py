"""``hil bench sweep``: what the sweep engine costs and what a worker is worth, measured back to back.

One sweep of ``--points`` points of about a second each (FFCC-a, ``nlls``, in-process lockstep, 1 s
simulated; the run seeds drawn at run time unless ``--seed``, and printed) runs on clusters whose
workers have already run one point (imports and caches warm, not timed):

1. a local cluster of 1 worker (``hil sweep --workers 1``), then
2. a local cluster of 2 workers (one per core of a 2-core machine), back to back, ``--rounds`` times
   (alternating, so a change in the machine's load falls on both);
3. once, a ``dask scheduler --host 127.0.0.1`` and two ``dask worker ... --nthreads 1`` processes started
   separately, as a cluster of machines would be (``hil sweep --scheduler tcp://127.0.0.1:PORT``).

Figures, with the 1-minute load average before and after each phase beside them:

- makespan: from the first point sent to the last row written;
- parallel efficiency = makespan(1 worker) / (2 x makespan(2 workers)) per round, and its median;
- CPU / wall per point: below 100 % a worker waited for a core (another process had it);
- overhead per point: the time a worker is not running a point between two of its points (median of the
  gaps between one point's end and the worker's next point's start: scheduling, moving the result,
  fetching the next), and ``(workers x makespan - sum of point times) / points`` (the same plus the idle
  tail), and the client's time to write one row;
- points per hour per core = points / (makespan in hours x workers);
- whether the three tables are the same (``hil.sweep.table.comparable``: the same rows and result
  columns, wall times, timings and workers aside).

``--report DIR`` writes DIR/sweep.md and DIR/sweep.json.
"""
from __future__ import annotations

import json
import os
import platform
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ..errors import ClusterError, ConfigError
from ..sweep.driver import run_sweep
from ..sweep.engine import Engine
from ..sweep.point import THREAD_ENV, run_point, threads_seen
from ..sweep.spec import parse_sweep
from ..sweep.table import comparable
from .. import terminal

BASE = Path(__file__).resolve().parents[2] / "scenarios" / "ffcc_a.toml"


def register(sub) -> None:
    p = sub.add_parser("sweep", help="the sweep engine: 1 vs 2 local Dask workers, a separately started "
                       "scheduler and workers; efficiency, overhead per point, points per hour per core")
    p.add_argument("--points", type=int, default=24, help="points per phase (default 24)")
    p.add_argument("--seed", type=int, default=None, help="master seed of the run seeds (default: drawn now, printed)")
    p.add_argument("--duration-s", type=float, default=1.0, help="simulated seconds per point (default 1.0: "
                   "about a second of wall time per point on a 2-core machine)")
    p.add_argument("--rounds", type=int, default=2, help="times the 1-worker and the 2-worker phases alternate "
                   "(default 2; the efficiency of each round and their median are reported)")
    p.add_argument("--no-external", action="store_true", help="skip the separately started scheduler and workers")
    p.add_argument("--report", metavar="DIR", default=None, help="write DIR/sweep.md and DIR/sweep.json")
    p.add_argument("--markdown", action="store_true", help="print the report as markdown (every column and the "
                   "notes; what --report writes to sweep.md)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.set_defaults(func=cmd_sweep_bench)


def make_sweep(points: int, seed: int, duration_s: float):
    import numpy as np

    seeds = [int(x) for x in np.random.default_rng([seed, 0xB5]).integers(1, 2 ** 31 - 1, points)]
    data = {"name": "bench", "base": str(BASE), "transport": "inprocess", "strategy": "nlls",
            "set": {"run.duration_s": duration_s}, "axes": {"seed": {"values": seeds}}}
    return parse_sweep(data, f"bench sweep (seed {seed})", BASE.parent)


def phase_figures(doc: dict, df, workers: int) -> dict:
    """The figures of one phase from the driver's result and its table (module docstring)."""
    import numpy as np

    gaps = []
    for _, rows in df.sort_values("t_start").groupby("worker"):
        starts, ends = rows["t_start"].to_numpy(), rows["t_end"].to_numpy()
        gaps += list(starts[1:] - ends[:-1])
    makespan = doc["wall_s"]
    busy = float(df["point_wall_s"].sum())
    n = len(df)
    return {"workers": workers, "points": n, "makespan_s": makespan,
            "point_s_median": float(df["point_wall_s"].median()),
            "run_wall_s_median": float(df["wall_s"].median()),
            "cpu_share_median": float((df["point_cpu_s"] / df["point_wall_s"]).median()),
            "point_cpu_s_median": float(df["point_cpu_s"].median()),
            "gap_ms_median": float(np.median(gaps) * 1e3) if gaps else None,
            "gap_ms_p90": float(np.percentile(gaps, 90) * 1e3) if gaps else None,
            "overhead_ms_per_point": (workers * makespan - busy) / n * 1e3,
            "persist_ms_median": doc["persist_ms_median"],
            "points_per_hour_per_core": n / (makespan / 3600.0) / workers,
            "workers_seen": int(df["worker"].nunique()), "failed": int(df["error"].notna().sum()),
            "engine_start_s": doc["engine_start_s"]}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dask_cli() -> list[str]:
    exe = Path(sys.executable).parent / "dask"
    found = str(exe) if exe.exists() else shutil.which("dask")
    if not found:
        raise ClusterError("the dask command is not installed beside this Python (pip install 'dask[distributed]')")
    return [found]


class ExternalCluster:
    """``dask scheduler`` and ``workers`` x ``dask worker`` as separate processes on 127.0.0.1 (stopped on exit)."""

    def __init__(self, workers: int = 2):
        self.workers = workers
        self.port = _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.procs: list[subprocess.Popen] = []
        self.logdir = tempfile.TemporaryDirectory(prefix="hil-bench-sweep-")

    def __enter__(self):
        dask = _dask_cli()
        env = {**os.environ, **THREAD_ENV}
        log = open(Path(self.logdir.name) / "scheduler.log", "w")
        self.procs.append(subprocess.Popen(dask + ["scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                                                   "--no-dashboard"], stdout=log, stderr=subprocess.STDOUT, env=env))
        for i in range(self.workers):
            log = open(Path(self.logdir.name) / f"worker{i}.log", "w")
            self.procs.append(subprocess.Popen(dask + ["worker", self.address, "--nthreads", "1", "--nworkers", "1",
                                                       "--host", "127.0.0.1", "--no-dashboard", "--name", f"w{i}"],
                                               stdout=log, stderr=subprocess.STDOUT, env=env))
        return self

    def __exit__(self, *exc):
        for p in reversed(self.procs):          # workers first, then the scheduler
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:  # a worker that ignores SIGTERM is killed
                p.kill()
                p.wait()
        self.logdir.cleanup()


def run_phase(label: str, sweep, out: Path, engine_kwargs: dict, workers: int, log) -> tuple[dict, object]:
    import pandas as pd

    load_before = os.getloadavg()[0]
    with Engine(**engine_kwargs) as engine:
        warm = sweep.task(sweep.points[0])
        engine.warm_up(run_point, {**warm, "key": "warm-up", "index": -1})
        threads = engine.run_on_workers(threads_seen)
        log(f"bench sweep: {label}: {engine.describe()}, warm; {len(sweep.points)} points")
        doc = run_sweep(sweep, out, engine=engine, progress=None, log=lambda text: None)
    df = pd.read_parquet(out / "table")
    fig = phase_figures(doc, df, workers)
    fig.update(label=label, load_before=load_before, load_after=os.getloadavg()[0],
               threads_one_per_worker=all(all(v in ("1", 1) for v in t.values()) for t in threads.values()),
               threads_seen=threads)
    log(f"bench sweep: {label}: makespan {fig['makespan_s']:.1f} s, {fig['points_per_hour_per_core']:.0f} points/h/core, "
        f"gap {fig['gap_ms_median']:.1f} ms, load {load_before:.2f} -> {fig['load_after']:.2f}")
    return fig, df


def cmd_sweep_bench(args) -> int:
    if args.points < 4:
        raise ConfigError("--points: must be >= 4")
    if args.rounds < 1:
        raise ConfigError("--rounds: must be >= 1")
    if not 0.6 <= args.duration_s <= 60:
        raise ConfigError("--duration-s: must be in [0.6, 60] (the fault is at 0.5 s)")
    seed = secrets.randbits(31) if args.seed is None else args.seed
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    log(f"bench sweep: {args.points} points per phase, run seeds from master seed {seed} (repeat with --seed {seed})")
    sweep = make_sweep(args.points, seed, args.duration_s)
    phases, tables = [], {}
    with tempfile.TemporaryDirectory(prefix="hil-bench-sweep-") as tmp:
        tmp = Path(tmp)
        for r in range(args.rounds):          # 1 and 2 workers alternate: a change of the machine's load
            for label, kwargs, n in (("local, 1 worker", {"workers": 1}, 1), ("local, 2 workers", {"workers": 2}, 2)):
                name = f"{label} (round {r + 1})"
                fig, tables[name] = run_phase(name, sweep, tmp / f"r{r}-{n}", kwargs, n, log)
                fig.update(round=r + 1)
                phases.append(fig)
        if not args.no_external:
            with ExternalCluster(2) as cluster:
                label = "dask scheduler + 2 dask worker processes"
                fig, tables[label] = run_phase(label, sweep, tmp / "external", {"scheduler": cluster.address,
                                                                                 "workers": 2}, 2, log)
                phases.append(fig)
    import numpy as np

    rounds = [(p1, p2) for p1, p2 in zip(phases[0::2], phases[1::2]) if p1.get("round")]
    efficiencies = [p1["makespan_s"] / (2 * p2["makespan_s"]) for p1, p2 in rounds]
    efficiency = float(np.median(efficiencies))
    reference = comparable(tables["local, 2 workers (round 1)"])
    same = {label: bool(comparable(df).equals(reference)) for label, df in tables.items()}
    doc = {"seed": seed, "points": args.points, "duration_s": args.duration_s, "cores": os.cpu_count(),
           "machine": platform.machine(), "utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "parallel_efficiency": efficiency, "parallel_efficiency_per_round": efficiencies, "phases": phases,
           "same_table_as_local_2_workers": same, "thread_env": THREAD_ENV}
    text = markdown(doc)
    if args.report:
        out = Path(args.report)
        out.mkdir(parents=True, exist_ok=True)
        (out / "sweep.json").write_text(json.dumps(doc, indent=1) + "\n")
        (out / "sweep.md").write_text(text)
        log(f"bench sweep: wrote {out / 'sweep.md'} and {out / 'sweep.json'}")
    print(json.dumps(doc) if args.json else text if args.markdown else terminal_text(doc))
    return 0


def terminal_text(doc: dict) -> str:
    """The columns a reader decides on, within ``terminal.WIDTH``; every column with ``--markdown``."""
    f = lambda x, spec: "n/a" if x is None else format(x, spec)  # noqa: E731
    head = ["phase", "makespan s", "CPU / wall", "gap ms", "overhead ms", "pts/h/core", "same table"]
    rows = [[p["label"].replace("2 dask worker processes", "2 workers"), f"{p['makespan_s']:.1f}", f"{p['cpu_share_median'] * 100:.0f} %",
             f(p["gap_ms_median"], ".1f"), f"{p['overhead_ms_per_point']:.0f}", f"{p['points_per_hour_per_core']:.0f}",
             "yes" if doc["same_table_as_local_2_workers"].get(p["label"]) else "NO"] for p in doc["phases"]]
    per_round = ", ".join(f"{e * 100:.0f} %" for e in doc["parallel_efficiency_per_round"])
    return "\n".join([terminal.wrap(f"hil bench sweep: {doc['points']} points per phase, seed {doc['seed']}, "
                                     f"{doc['cores']} cores"), "", terminal.columns(head, rows), "",
                      terminal.wrap(f"Parallel efficiency, 2 local workers against 1: "
                                    f"{doc['parallel_efficiency'] * 100:.0f} % (median over rounds: {per_round}). "
                                    "Medians per point; every column and the notes: --markdown.")])


def markdown(doc: dict) -> str:
    f = lambda x, spec: "n/a" if x is None else format(x, spec)  # noqa: E731
    cmd = f"hil bench sweep --points {doc['points']} --rounds {len(doc['parallel_efficiency_per_round'])} --seed {doc['seed']}"
    lines = [f"# {cmd}", "",
             f"Written by `{cmd} --report docs/benchmarks` on {doc['utc']}, "
             f"{doc['machine']}, {doc['cores']} cores (shared: see the load averages).  Each point: FFCC-a, `nlls`, "
             f"in-process lockstep, {doc['duration_s']:g} s simulated, run seeds drawn from the master seed.  Every "
             "cluster's workers ran one point before the clock started.", "",
             "| phase | workers | makespan s | point s (median) | point CPU s (median) | CPU / wall per point (median) | gap between a worker's points ms (median / p90) | "
             "overhead ms per point (idle tail included) | row write ms | points per hour per core | load before → after | same table | 1 thread per worker |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for p in doc["phases"]:
        lines.append(f"| {p['label']} | {p['workers']} | {p['makespan_s']:.1f} | {p['point_s_median']:.2f} | "
                     f"{p['point_cpu_s_median']:.2f} | {p['cpu_share_median'] * 100:.0f} % | "
                     f"{f(p['gap_ms_median'], '.1f')} / {f(p['gap_ms_p90'], '.1f')} | {p['overhead_ms_per_point']:.0f} | "
                     f"{f(p['persist_ms_median'], '.1f')} | {p['points_per_hour_per_core']:.0f} | "
                     f"{p['load_before']:.2f} → {p['load_after']:.2f} | "
                     f"{'yes' if doc['same_table_as_local_2_workers'].get(p['label']) else 'NO'} | "
                     f"{'yes' if p['threads_one_per_worker'] else 'NO'} |")
    per_round = ", ".join(f"{e * 100:.0f} %" for e in doc["parallel_efficiency_per_round"])
    lines += ["", f"Parallel efficiency, 2 local workers against 1: **{doc['parallel_efficiency'] * 100:.0f} %** "
              f"(median over rounds: {per_round}; per round, makespan of 1 worker / (2 x makespan of 2 workers), "
              "the two phases back to back).", "",
              "CPU / wall per point: the CPU time a worker process spent on a point over its wall time; below "
              "100 % the worker waited for a core (other processes on the machine: compare the load average).", "",
              "Gap: the time between one point's end and the same worker's next point's start (the scheduler's "
              "round trip, the result sent, the next task fetched): the engine's cost per point on a worker.  "
              "Overhead per point: (workers x makespan - the sum of the points' times) / points, which adds the idle "
              "tail when one worker finishes before the other.  Row write: the client's time to persist one row "
              "(one Parquet file), overlapped with the workers' runs.  Same table: `hil.sweep.table.comparable` "
              "equal to the 2-worker local table (the same rows and result columns; wall times, timings, heartbeat "
              "frame counts and workers aside).  1 thread per worker: every worker process had OMP, OpenBLAS, MKL, "
              "numba, vecLib and numexpr at one thread (`hil.sweep.point.THREAD_ENV`, set before the worker starts) "
              "and numba's thread count at 1.", ""]
    return "\n".join(lines)
