"""A whole sweep: the points not yet in the table sent to the engine, each row persisted as it arrives,
a progress bar with ETA on stderr, and at the end the summary and plots.

Output directory ``out`` (default ``logs/sweep-<name>``): ``table/`` (the Parquet dataset, ``hil.sweep.table``),
``sweep.json`` (the sweep's points and inputs), ``summary.md`` and ``sweep-<axis>.png``
(``hil.sweep.report``), ``logs/`` (with ``keep_logs``: each point's MCAP, on the worker's machine).

A directory that already holds rows is refused unless ``resume``: then the points whose key is in the
table are skipped and only the others run.  A point that fails is a row with its error; a call the
cluster could not complete (a point that kept killing workers) leaves no row, is counted in
``incomplete`` and raises ``ClusterError`` after the rest is saved, so ``--resume`` tries it again.
Ctrl-C stops the sweep; every row written so far stays.
"""
from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from pathlib import Path

from ..errors import ClusterError, ConfigError
from ..progress import Progress
from .engine import Engine
from .point import run_point
from .report import summary_markdown, write_plots
from .table import Table


def default_out(sweep) -> Path:
    return Path("logs") / f"sweep-{''.join(c if c.isalnum() or c in '._-' else '_' for c in sweep.name)[:60]}"


def _eta(seconds: float) -> str:
    if seconds != seconds or seconds == float("inf"):
        return "?"
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}" if seconds >= 3600 \
        else f"{seconds // 60}:{seconds % 60:02d}"


def run_sweep(sweep, out=None, *, scheduler: str | None = None, workers: int | None = None, resume: bool = False,
              keep_logs: bool = False, dashboard: bool = False, progress: bool | None = None,
              log=None, engine: Engine | None = None) -> dict:
    """Run ``sweep`` (``spec.Sweep``); returns what ``hil sweep --json`` prints (module docstring).
    ``engine``: an entered ``Engine`` to use (and leave open) instead of starting one.  ``wall_s`` is from the
    first point sent to the last row written (the cluster's start is ``engine_start_s``); ``persist_ms_median``
    the time to write one row."""
    log = log or (lambda text: print(text, file=sys.stderr, flush=True))
    out = Path(out) if out else default_out(sweep)
    table = Table(out / "table", sweep.axes)
    done = table.done_keys()
    if done and not resume:
        raise ConfigError(f"--out {out}: holds {len(done)} finished points of a sweep already; add --resume to run "
                          "only the missing ones, or choose another --out")
    table.prepare()
    (out / "sweep.json").write_text(json.dumps({
        "sweep": sweep.path, "base": sweep.base_path, "transport": sweep.transport, "strategy": sweep.strategy,
        "seed": sweep.seed, "set": sweep.overrides, "family": sweep.family, "axes": sweep.axes,
        "points": [{"point": p.index, "key": p.key, "inputs": p.inputs} for p in sweep.points]}) + "\n")
    todo = [p for p in sweep.points if p.key not in done]
    keys = {p.key for p in sweep.points}
    skipped = len(sweep.points) - len(todo)
    logs_dir = str((out / "logs").resolve()) if keep_logs else None
    tasks = [sweep.task(p, logs_dir) for p in todo]
    incomplete, failed, written, persist_s = [], 0, 0, []
    wall = engine_start = 0.0
    engine_desc = None
    if tasks:
        start0 = time.perf_counter()
        with (contextlib.nullcontext(engine) if engine is not None else
              Engine(scheduler, workers, dashboard=dashboard)) as engine:
            engine_start = time.perf_counter() - start0
            wall0 = time.perf_counter()
            engine_desc = engine.describe()
            log(f"hil sweep: {len(sweep.points)} points ({skipped} already in {table.directory}, {len(tasks)} to run) "
                f"on {engine_desc}")
            if dashboard and engine.client is not None:
                log(f"hil sweep: dashboard {engine.client.dashboard_link}")
            bar = Progress(len(tasks), f"hil sweep {sweep.name}", progress)
            t0 = time.monotonic()
            try:
                for i, row in engine.map_unordered(run_point, tasks):
                    if isinstance(row, BaseException):
                        incomplete.append((todo[i].index, f"{type(row).__name__}: {' '.join(str(row).split())[:300]}"))
                    else:
                        t_write = time.perf_counter()
                        table.write(row)
                        persist_s.append(time.perf_counter() - t_write)
                        written += 1
                        failed += row["error"] is not None
                    n = written + len(incomplete)
                    rate = (time.monotonic() - t0) / n
                    bar.update(n, f"{n}/{len(tasks)} points, {failed} failed, ETA {_eta(rate * (len(tasks) - n))}")
            except KeyboardInterrupt:
                bar.close()
                log(f"hil sweep: interrupted after {written} of {len(tasks)} points; they are in {table.directory} "
                    f"(--resume runs the other {len(tasks) - written})")
                raise
            bar.close()
            wall = time.perf_counter() - wall0
    else:
        log(f"hil sweep: all {len(sweep.points)} points are in {table.directory} already")
    df = table.read()
    df = df[df["key"].isin(keys)].reset_index(drop=True)
    title = f"hil sweep {sweep.path}"
    notes = [f"Base scenario `{sweep.base_path}`, transport `{sweep.transport}`, strategy `{sweep.strategy}` "
             f"unless an axis sets it, fixed overrides {json.dumps(sweep.overrides)}"
             + (f", fault curves from family `{sweep.family['family']}` seed {sweep.family['seed']}"
                if sweep.family else "") + ".",
             f"Run on: {engine_desc or 'nothing new (resumed a finished sweep)'}; {len(tasks)} points run now in "
             f"{wall:.1f} s, {skipped} taken from the table; load average {os.getloadavg()[0]:.2f} at the end."]
    summary_path = out / "summary.md"
    summary_path.write_text(summary_markdown(df, sweep.axes, title, notes) + "\n")
    plots = write_plots(df, sweep.axes, out)
    doc = {"sweep": sweep.path, "out": str(out), "table": str(table.directory), "points": len(sweep.points),
           "ran_now": written, "skipped": skipped, "failed": int(df["error"].notna().sum()) if len(df) else 0,
           "incomplete": len(incomplete), "rows": len(df), "wall_s": wall, "engine_start_s": engine_start,
           "persist_ms_median": float(sorted(persist_s)[len(persist_s) // 2] * 1e3) if persist_s else None,
           "engine": engine_desc,
           "summary": str(summary_path), "plots": [str(p) for p in plots]}
    if incomplete:
        for index, why in incomplete[:5]:
            log(f"hil sweep: point {index} not completed by the cluster: {why}")
        raise ClusterError(f"{len(incomplete)} points were not completed by the cluster (first: point "
                           f"{incomplete[0][0]}: {incomplete[0][1][:150]}); the other rows are saved, --resume "
                           "runs the missing ones")
    return doc
