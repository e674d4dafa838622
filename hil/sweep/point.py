"""One sweep point on a worker: its scenario, one run, its row.

``run_point(task)`` takes the plain data of ``Sweep.task`` (it travels to other machines: the base
scenario goes as text, never as a path the worker may not have) and returns a dict: ``index``,
``key``, ``inputs``, ``result`` (the ``hil run --json`` summary, or the partial one of a faulted run,
or None), ``error`` (one line, or None), ``truth`` (the true fault curve's peak and law),
``point_wall_s`` (the whole point on the worker: building the scenario, the run, the summary) and
``point_cpu_s`` (the CPU time the worker process spent on it: below the wall time when it waited for a core),
``t_start``/``t_end`` (the worker's wall clock, for the benchmark's overhead figures) and ``worker``
(the Dask worker's address, else ``host:pid``).  A failing point never raises: its error is its row
(``KeyboardInterrupt`` and ``SystemExit`` do raise).

Transports: ``inprocess`` is ``hil run --bus inprocess`` (lockstep, the TCU node in the same thread);
``process`` is ``hil run --bus local`` (the TCU a child process on a relay-free local bus made for the
point, so points on one machine never share a bus; the scenario is written to a temporary file the
TCU process reads).  Logs are written only with ``keep_logs_dir`` (one sub-directory per point, on
the worker's machine).
"""
from __future__ import annotations

import os
import socket
import time
from pathlib import Path

#: the environment a worker process needs before it imports numpy / numba: one thread each
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1"}


def threads_seen() -> dict:
    """What this process runs numerical code with: the ``THREAD_ENV`` variables and numba's thread count."""
    out = {k: os.environ.get(k) for k in THREAD_ENV}
    try:
        import numba

        out["numba_threads"] = numba.config.NUMBA_NUM_THREADS
    except ImportError:  # numba absent: no thread count to record
        out["numba_threads"] = None
    return out


def worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):  # not on a Dask worker (or none installed): host and pid name it
        return f"{socket.gethostname()}:{os.getpid()}"


def point_scenario(task: dict):
    """The point's scenario: the base (or the family draw on it), [set] and the point's field values
    applied, its --reality effects merged.  Raises ``ConfigError`` / ``ValueError``."""
    from ..config import parse_scenario
    from ..effects import parse_effect, with_reality
    from .spec import reality_items

    inputs = task["inputs"]
    text, path = task["base_text"], task["base_path"]
    if "family" in inputs:
        from plant import families

        fam = task["family"]
        text = families.draw_scenario_text(text, fam["family"], fam["seed"], int(inputs["family"]))
        path = f"{fam['family']} draw {inputs['family']} of seed {fam['seed']}"
    overrides = dict(task["set"])
    overrides.update({k: v for k, v in inputs.items() if "." in k})
    scenario = parse_scenario(text, path, overrides)
    effects = reality_items(inputs.get("reality", ""), ValueError)
    if effects:
        scenario = with_reality(scenario, dict(parse_effect(e) for e in effects))
    return scenario


def _truth(scenario) -> dict:
    curve = scenario.fault_curve
    v_peak, mu_peak = curve.peak()
    return {"true_peak_mu": float(mu_peak), "true_peak_creep_kmh": float(v_peak),
            "fault_law": "polach" if type(curve).__name__ == "PolachCurve" else "exp"}


def run_point(task: dict) -> dict:
    """The point's row (module docstring); never raises for a failing run."""
    from ..errors import HilError, PeerSilent
    from ..exchange import run

    t_start = time.time()
    t0, cpu0 = time.perf_counter(), time.process_time()
    row = {"index": task["index"], "key": task["key"], "inputs": task["inputs"], "result": None, "error": None,
           "truth": None, "worker": worker_name()}
    try:
        scenario = point_scenario(task)
        row["truth"] = _truth(scenario)
        inputs = task["inputs"]
        strategy = inputs.get("strategy", task["strategy"])
        seed = inputs.get("seed", task["seed"])
        out_dir = None
        if task.get("keep_logs_dir"):
            out_dir = str(Path(task["keep_logs_dir"]) / f"{task['index']:07d}-{task['key']}")
        kwargs = dict(out_dir=out_dir, record=out_dir is not None, progress=False, log=lambda text: None)
        if task["transport"] == "process":        # the TCU process is handed this scenario (Scenario.handover)
            row["result"] = run(scenario, strategy, seed, bus="local", **kwargs)
        else:
            row["result"] = run(scenario, strategy, seed, bus="inprocess", **kwargs)
    except PeerSilent as e:
        row["result"] = getattr(e, "summary", None)
        row["error"] = _one_line(e)
    except (HilError, ValueError, ArithmeticError) as e:
        row["error"] = _one_line(e)
    except Exception as e:  # noqa: BLE001 - a point's failure is its row, never the sweep's end
        row["error"] = f"{type(e).__name__}: {_one_line(e)}"
    row["point_wall_s"] = time.perf_counter() - t0
    row["point_cpu_s"] = time.process_time() - cpu0
    row["t_start"], row["t_end"] = t_start, time.time()
    return row


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text[:500]
