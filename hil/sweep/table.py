"""The sweep's table: a Parquet dataset directory, one file per finished point, written as it arrives.

``pandas.read_parquet(DIR)`` opens it (one row per point).  Every file of a sweep has the same schema
(``schema(axes)``), so the dataset never depends on which point finished first:

- ``point`` (its index in the sweep), ``key`` (``spec.Point.key``), ``error`` (one line, null when it ran),
  ``worker``, ``point_wall_s`` and ``point_cpu_s`` (the point on its worker: wall and CPU time),
  ``t_start``/``t_end`` (the worker's clock, Unix s), ``finished_utc``;
- ``in.<axis>``: the point's inputs (numbers, strings, booleans; a list, e.g. several effects, as JSON);
- the main ``hil run --json`` figures as typed columns (``OUTPUT_COLUMNS``), ``correct`` (confirmed with
  peak mu within 3 % and peak creep within 10 % of the truth: ``hil/benchmarks/judge.py``'s rule) and the
  truth (``true_peak_mu``, ``true_peak_creep_kmh``, ``fault_law``);
- ``result_json``: the whole ``hil run --json`` object of the point (every key, lists and tables too).

A file is written under a dot-name and renamed into place, so a reader (or ``--resume`` after a kill)
never sees half a row; ``done_keys`` reads the keys from the file names.  "The same table" (a local
cluster against a remote one, Dask against serial) means ``comparable(df)`` equal: the same rows and
result columns with wall times, timings and the worker left out (``TIMING_COLUMNS``, ``TIMING_KEYS``).
"""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

#: the same tolerances as hil/benchmarks/judge.py (tests/test_sweep.py checks they agree)
TOL_PEAK_MU_PERCENT = 3.0
TOL_PEAK_CREEP_PERCENT = 10.0

OUTPUT_COLUMNS = {
    "scenario": "string", "strategy": "string", "seed": "int64", "bus": "string", "mode": "string",
    "transport": "string", "plant": "string", "identified": "bool", "unconfirmed": "bool", "false_alarm": "bool",
    "t_fault_s": "float64", "t_serious_s": "float64", "t_det_s": "float64", "t_detected_s": "float64",
    "t_identified_s": "float64", "rt_percent": "float64", "mse": "float64", "rmse": "float64", "mae": "float64",
    "r2": "float64", "peak_mu": "float64", "peak_creep_kmh": "float64", "peak_mu_err_percent": "float64",
    "peak_creep_err_percent": "float64", "curve_rmse_vs_truth": "float64", "r2_vs_truth": "float64",
    "r2_vs_truth_to_peak": "float64", "observer_lag_ms": "float64", "corrections": "int64", "samples": "int64",
    "bus_load_percent": "float64", "frames_tx": "int64", "frames_rx": "int64", "sim_s": "float64",
    "wall_s": "float64", "fault": "string", "mcap": "string", "control": "string",
    "adhesion_utilisation": "float64", "adhesion_utilisation_low": "float64", "macro_slip_s": "float64",
    "macro_slip_count": "int64",
}
META_COLUMNS = {"point": "int64", "key": "string", "error": "string", "worker": "string", "point_wall_s": "float64",
                "point_cpu_s": "float64", "t_start": "float64", "t_end": "float64", "finished_utc": "string"}
DERIVED_COLUMNS = {"correct": "bool", "true_peak_mu": "float64", "true_peak_creep_kmh": "float64",
                   "fault_law": "string", "result_json": "string"}
#: columns that differ between two runs of the same point (clocks, places)
#: (frames_tx and frames_rx count the heartbeats too, which are paced by the wall clock)
TIMING_COLUMNS = ("worker", "point_wall_s", "point_cpu_s", "t_start", "t_end", "finished_utc", "wall_s", "mcap",
                  "frames_tx", "frames_rx")
#: keys of ``result_json`` that differ between two runs of the same point
TIMING_KEYS = ("wall_s", "sim_s_per_wall_s", "round_trip_p50_us", "round_trip_p99_us", "jitter_p50_us",
               "jitter_p99_us", "jitter_max_us", "mcap", "frames_tx", "frames_rx")
INPUT_PREFIX = "in."


def input_type(values: list) -> str:
    if all(isinstance(v, bool) for v in values):
        return "bool"
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return "int64"
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return "float64"
    if all(isinstance(v, str) for v in values):
        return "string"
    return "json"          # stored as a JSON string


def schema(axes: dict):
    """The pyarrow schema of every file of a sweep with these axes ({field: values})."""
    import pyarrow as pa

    types = {"int64": pa.int64(), "float64": pa.float64(), "bool": pa.bool_(), "string": pa.string(),
             "json": pa.string()}
    fields = [pa.field(k, types[t]) for k, t in META_COLUMNS.items()]
    fields += [pa.field(INPUT_PREFIX + name, types[input_type(values)]) for name, values in axes.items()]
    fields += [pa.field(k, types[t]) for k, t in {**OUTPUT_COLUMNS, **DERIVED_COLUMNS}.items()]
    return pa.schema(fields)


def _number(v, kind):
    if v is None or isinstance(v, bool) and kind != "bool":
        return None
    if kind == "float64":
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None
    if kind == "int64":
        return int(v) if isinstance(v, (int, float)) and math.isfinite(v) else None
    if kind == "bool":
        return bool(v) if isinstance(v, bool) else None
    return v if isinstance(v, str) else json.dumps(v)


def correct(result: dict | None) -> bool | None:
    """hil/benchmarks/judge.py's verdict from a summary: confirmed with both peaks within tolerance."""
    if not result:
        return None
    mu, creep = result.get("peak_mu_err_percent"), result.get("peak_creep_err_percent")
    return bool(result.get("identified") and not result.get("unconfirmed") and mu is not None and creep is not None
                and mu <= TOL_PEAK_MU_PERCENT and creep <= TOL_PEAK_CREEP_PERCENT)


def to_record(row: dict, axes: dict) -> dict:
    """A ``point.run_point`` row as one record of ``schema(axes)``."""
    result = row.get("result") or {}
    truth = row.get("truth") or {}
    rec = {"point": row["index"], "key": row["key"], "error": row.get("error"), "worker": row.get("worker"),
           "point_wall_s": row.get("point_wall_s"), "point_cpu_s": row.get("point_cpu_s"),
           "t_start": row.get("t_start"), "t_end": row.get("t_end"),
           "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    for name, values in axes.items():
        kind = input_type(values)
        v = row["inputs"].get(name)
        rec[INPUT_PREFIX + name] = json.dumps(v) if kind == "json" else _number(v, kind)
    for k, kind in OUTPUT_COLUMNS.items():
        rec[k] = _number(result.get(k), kind)
    rec["correct"] = correct(row.get("result"))
    rec["true_peak_mu"] = truth.get("true_peak_mu")
    rec["true_peak_creep_kmh"] = truth.get("true_peak_creep_kmh")
    rec["fault_law"] = truth.get("fault_law")
    rec["result_json"] = json.dumps(row["result"]) if row.get("result") is not None else None
    return rec


class Table:
    """The dataset directory ``directory`` of a sweep with ``axes``."""

    def __init__(self, directory, axes: dict):
        self.directory = Path(directory)
        self.axes = axes
        self.schema = schema(axes)

    def prepare(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        for stale in self.directory.glob(".part-*"):        # a write cut short by a kill
            stale.unlink(missing_ok=True)

    def done_keys(self) -> set[str]:
        if not self.directory.is_dir():
            return set()
        return {p.stem.split("-")[2] for p in self.directory.glob("part-*.parquet") if p.stem.count("-") >= 2}

    def write(self, row: dict) -> Path:
        """Persist one point's row now (one small file, renamed into place)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        name = f"part-{row['index']:07d}-{row['key']}.parquet"
        tmp = self.directory / f".{name}.{os.getpid()}"
        pq.write_table(pa.Table.from_pylist([to_record(row, self.axes)], schema=self.schema), tmp)
        final = self.directory / name
        os.replace(tmp, final)
        return final

    def read(self):
        """The whole table as a pandas DataFrame, sorted by point."""
        import pandas as pd

        if not any(self.directory.glob("part-*.parquet")):
            return pd.DataFrame({f.name: pd.Series(dtype=object) for f in self.schema})
        df = pd.read_parquet(self.directory)
        return df.sort_values("point", kind="stable").reset_index(drop=True)


def comparable(df):
    """``df`` without what differs between two runs of the same points (module docstring), sorted by point;
    ``result_json`` parsed, its timing keys dropped, and written back with sorted keys."""
    out = df.drop(columns=[c for c in TIMING_COLUMNS if c in df.columns]).sort_values("point").reset_index(drop=True)

    def strip(text):
        if text is None or (isinstance(text, float) and math.isnan(text)):
            return None
        d = json.loads(text)
        return json.dumps({k: v for k, v in d.items() if k not in TIMING_KEYS}, sort_keys=True)

    out["result_json"] = out["result_json"].map(strip)
    return out
