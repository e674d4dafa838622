"""Where points run: Dask (``dask.distributed``), or this process one after another.

``Engine(scheduler=None, workers=None)`` used as a context manager:

- ``scheduler`` None and ``workers`` not 0: a ``distributed.LocalCluster`` started here and stopped on
  exit: ``workers`` worker processes (default ``os.cpu_count()``), one thread each, bound to
  127.0.0.1, dashboard off unless ``dashboard`` (then on 127.0.0.1:8787).  Each worker's nanny sets
  ``THREAD_ENV`` (OMP, OpenBLAS, MKL, numba ... at one thread) before the worker process starts, so
  before it imports numpy or numba; a worker that dies (SIGKILL, out of memory) is restarted by its
  nanny and the scheduler runs its unfinished points again elsewhere.
- ``scheduler="tcp://HOST:PORT"``: a client of that cluster (``dask scheduler`` / ``dask worker``
  started by someone else); it waits up to ``connect_timeout_s`` for the scheduler and one worker.
- ``workers=0`` and no scheduler: no Dask at all, every point in this process in order (what the
  benches do by default, and the reference the parallel results are checked against).

``map_unordered(fn, items)`` yields ``(i, value)`` as each ``fn(items[i])`` finishes, in completion
order; ``value`` is the exception when the call raised (or, on Dask, when it could not be completed:
``KilledWorker`` after a point took down ``distributed.scheduler.allowed-failures`` workers).  At most
``window`` calls are queued on the cluster at once, so a sweep of a million points does not hold a
million futures.  There is no scheduler or pool here: Dask schedules, retries and balances.
"""
from __future__ import annotations

import logging
import os
import signal
import threading
import time

from ..errors import ClusterError
from .point import THREAD_ENV

CONNECT_TIMEOUT_S = 30.0


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


class Engine:
    def __init__(self, scheduler: str | None = None, workers: int | None = None, *, dashboard: bool = False,
                 connect_timeout_s: float = CONNECT_TIMEOUT_S, window: int | None = None):
        if workers is not None and workers < 0:
            raise ClusterError(f"--workers {workers}: must be >= 0")
        if scheduler is not None and workers == 0:
            raise ClusterError("--workers 0 (this process) and --scheduler exclude each other")
        self.scheduler = scheduler
        self.serial = scheduler is None and workers == 0
        self.workers = workers
        self.dashboard = dashboard
        self.connect_timeout_s = connect_timeout_s
        self.window = window
        self.cluster = self.client = None

    # -- life cycle -------------------------------------------------------------------------------
    def __enter__(self) -> "Engine":
        if self.serial:
            return self
        try:
            from distributed import Client, LocalCluster
        except ImportError as e:
            raise ClusterError(f"dask.distributed is not installed ({e}); pip install 'dask[distributed]'") from None
        try:
            self._start(Client, LocalCluster)
        except BaseException:         # Ctrl-C or a failure while starting: stop what did start
            self.close()
            raise
        return self

    def _start(self, Client, LocalCluster) -> None:
        if self.scheduler is None:
            n = self.workers or os.cpu_count() or 1
            # the worker processes start with SIGINT ignored (inherited through exec): a terminal's Ctrl-C
            # reaches the whole process group, and only this process handles it (it closes the cluster)
            previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if _main_thread() else None
            try:
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                            dashboard_address="127.0.0.1:8787" if self.dashboard else None,
                                            # CRITICAL: a worker's heartbeat racing the cluster's close logs a
                                            # CommClosedError traceback at ERROR after the results are in (seen
                                            # at the end of a 200-draw bench); a task's failure still reaches
                                            # the client as its exception
                                            silence_logs=logging.CRITICAL, env=dict(THREAD_ENV))
            finally:
                if previous is not None:
                    signal.signal(signal.SIGINT, previous)
            self.client = Client(self.cluster)
            self.client.wait_for_workers(n, timeout=self.connect_timeout_s)
        else:
            if not self.scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://", "ws://", "wss://")):
                raise ClusterError(f"--scheduler {self.scheduler!r}: expected an address like tcp://HOST:PORT")
            try:
                self.client = Client(self.scheduler, timeout=f"{self.connect_timeout_s}s")
                self.client.wait_for_workers(self.workers or 1, timeout=self.connect_timeout_s)
            except (OSError, TimeoutError) as e:
                why = " ".join(str(e).split())[:200]
                raise ClusterError(f"--scheduler {self.scheduler}: no cluster with a worker answered within "
                                   f"{self.connect_timeout_s:g} s ({type(e).__name__}: {why})") from None

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            except Exception:  # noqa: BLE001 - closing after an interrupt may find the loop gone
                pass
            self.client = None
        if self.cluster is not None:
            try:
                self.cluster.close()
            except Exception:  # noqa: BLE001
                pass
            self.cluster = None

    # -- facts -------------------------------------------------------------------------------------
    @property
    def nworkers(self) -> int:
        if self.serial:
            return 1
        return len(self.client.scheduler_info(n_workers=-1)["workers"]) if self.client else 0

    @property
    def address(self) -> str:
        if self.serial:
            return "this process"
        return self.client.scheduler.address if self.client else "closed"

    def describe(self) -> str:
        if self.serial:
            return "this process, one point after another"
        kind = "local cluster (started here)" if self.cluster is not None else "cluster"
        return f"{kind} at {self.address} with {self.nworkers} workers"

    def run_on_workers(self, fn) -> dict:
        """``fn()`` once on every worker: {worker address: value} (in this process: {"serial": value})."""
        if self.serial:
            return {"serial": fn()}
        return self.client.run(fn)

    def warm_up(self, fn, arg) -> dict:
        """``fn(arg)`` once on every worker, as a task pinned to it (imports, caches): {worker: value}."""
        if self.serial:
            return {"serial": fn(arg)}
        addresses = list(self.client.scheduler_info(n_workers=-1)["workers"])
        futures = {a: self.client.submit(fn, arg, workers=[a], allow_other_workers=False, pure=False)
                   for a in addresses}
        return {a: f.result() for a, f in futures.items()}

    # -- work --------------------------------------------------------------------------------------
    def map_unordered(self, fn, items):
        """Yield ``(i, fn(items[i]))`` (or ``(i, exception)``) as each finishes (module docstring)."""
        if self.serial:
            for i, item in enumerate(items):
                try:
                    yield i, fn(item)
                except (KeyboardInterrupt, SystemExit):
                    raise
                except Exception as e:  # noqa: BLE001 - the caller decides
                    yield i, e
            return
        from distributed import as_completed

        items = list(items)
        window = self.window or max(64, 8 * max(self.nworkers, 1))
        index = {}
        pending = iter(range(len(items)))

        def submit(i):
            fut = self.client.submit(fn, items[i], pure=False, key=f"hil-{i}-{time.monotonic_ns()}")
            index[fut.key] = (i, fut)
            return fut

        first = [submit(i) for _, i in zip(range(window), pending)]
        queue = as_completed(first)
        try:
            for fut in queue:
                i, _ = index.pop(fut.key)
                if fut.status == "finished":
                    value = fut.result()
                else:
                    try:
                        value = fut.exception()
                    except Exception as e:  # noqa: BLE001 - e.g. a cancelled future
                        value = e
                fut.release()
                nxt = next(pending, None)
                if nxt is not None:
                    queue.add(submit(nxt))
                yield i, value
        finally:
            for _, fut in index.values():        # an interrupted sweep leaves nothing queued
                fut.cancel()


def map_in_order(fn, items, scheduler: str | None = None, workers: int | None = None, on_result=None) -> list:
    """``[fn(x) for x in items]`` through an ``Engine``: in this process, one after another, when neither
    ``scheduler`` nor ``workers`` is given (the benches' default), else on Dask.  ``on_result(done, i)``
    after each call finishes.  The first exception of a call is raised (the others are cancelled), as the
    serial loop would.  ``fn`` and ``items`` must pickle (module-level functions, plain data)."""
    items = list(items)
    out = [None] * len(items)
    serial = scheduler is None and workers is None
    with Engine(scheduler, 0 if serial else workers) as engine:
        for done, (i, value) in enumerate(engine.map_unordered(fn, items), 1):
            if isinstance(value, BaseException):
                raise value
            out[i] = value
            if on_result is not None:
                on_result(done, i)
    return out
