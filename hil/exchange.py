"""The exchange loop: the ONLY plant-side loop of a HIL run, its timing, and ``run``, which runs it
inside the run's session (``hil.session``: bus, TCU, log and host tuning, and the failure path).

Per exchange period k the plant node senses, sends ``PlantSensor(k)`` and waits for ``TorqueCommand(k)``:

- ``lockstep``: it waits as long as the TCU needs (deterministic; as fast as the bus allows);
- ``realtime``: period k starts at ``t0 + k * period`` of the wall clock; the command must arrive
  before ``deadline_fraction`` of the period, otherwise the deadline is missed and the torque being
  applied is held.  Period jitter, lateness, round trip and misses go to ``/loop/timing``.

On a bus with a TCU's own DBC (``[bus] dbc``, ``hil/bus/mapping.py``) there are no step counters: the
first command frame after the period's frames is the period's command, waited for the same way.

The TCU on the other end is reached through one of three transports (``hil.session.Tcu``):

- ``inprocess`` (``bus="inprocess"``): a ``TcuNode`` answers in this thread, through the same DBC
  encode/decode (``hil.bus.link.InprocessTcuBus``): no second process, the same frames;
- ``process`` (default): ``python -m hil.tcu_node`` as a child process on the bus;
- ``external``: a TCU already on the bus (``hil tcu`` elsewhere, a real TCU) answers.

Whatever the transport, the summary comes from the run's ``Trace``, fed by the frames the plant
node received (results, samples, observer): an external TCU's run has fit metrics too.

A real-time run's summary (and so the log's) says whether its missed deadlines exceed
``[bus] max_missed_fraction`` (``deadlines_exceeded``); ``run`` still returns it, so benchmarks can
measure misses, and ``check_deadlines`` (called by ``hil run`` after the logs are written) turns it
into ``DeadlinesMissed`` (exit 5).

Faults: the TCU silent for longer than the limit, its process ending, its heartbeat saying "fault",
or (lockstep) no command for the pending step within ``[bus] lockstep_progress_s`` twice (``NoProgress``,
from ``PlantNode.await_command``) raise ``PeerSilent`` (exit 3); the log then holds the fault (an event and ``fault``
metadata) and is closed, and the exception carries the partial summary (``.summary``) with a
``fault`` field.  Ctrl-C and SIGTERM end the run as ``KeyboardInterrupt``, never mid-write.  A log
that cannot be written (disk full) raises ``LogWriteError``: the TCU is told the plant failed and
stopped, the bus closed, the log closed as far as the disk allows (an empty file removed).
"""
from __future__ import annotations

import contextlib
import gc
import math
import time

import numpy as np

from identifier import DEFAULT_STRATEGY
from identifier.messages import TorqueCommand

from .errors import DeadlinesMissed
from .log.record import write_timing
from .plant_node import PlantNode
from .progress import Progress
from .session import Session


@contextlib.contextmanager
def collector_paused(active: bool = True):
    """No garbage collection inside (when ``active``), as the real-time loops run: a full collection
    over scipy's and casadi's objects costs whole periods.  The objects alive on entry are frozen
    (never scanned again); on exit the collector is as it was."""
    if not active:
        yield
        return
    was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if was_enabled:
            gc.enable()


def _percentile(xs, q):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.percentile(xs, q)) if xs else None


class Timing:
    """Per-period wall-clock figures of the loop, recorded and summarised."""

    def __init__(self, period_s: float, mode: str, deadline_fraction: float = 0.9):
        self.period_s = period_s
        self.mode = mode
        self.deadline_us = deadline_fraction * period_s * 1e6
        self.period_us: list[float] = []
        self.round_trip_us: list[float] = []
        self.lateness_us: list[float] = []
        self.missed_steps: list[int] = []
        self.t0_s: float | None = None          # realtime: period 0's start on time.perf_counter

    @property
    def missed(self) -> int:
        return len(self.missed_steps)

    def summary(self, late_commands: int) -> dict:
        out = {"round_trip_p50_us": _percentile(self.round_trip_us, 50),
               "round_trip_p99_us": _percentile(self.round_trip_us, 99)}
        if self.mode == "realtime":
            nominal = self.period_s * 1e6
            jitter = [abs(p - nominal) for p in self.period_us if math.isfinite(p)]
            # a period the plant itself began after its deadline: its process did not run (a stall of the
            # process or its CPU), so no bus or TCU could have met that deadline
            started_late = sum(1 for k in self.missed_steps if self.lateness_us[k] >= self.deadline_us)
            out.update({"steps": len(self.period_us), "missed_deadlines": self.missed,
                        # period k began at t0 + k * period on CLOCK_MONOTONIC (perf_counter on Linux), a
                        # clock other processes share: a probe beside the run can place its events in periods
                        "t0_monotonic_s": self.t0_s,
                        "missed_deadlines_plant_started_late": started_late,
                        "jitter_p50_us": _percentile(jitter, 50), "jitter_p99_us": _percentile(jitter, 99),
                        "jitter_max_us": max(jitter) if jitter else None,
                        "lateness_p99_us": _percentile(self.lateness_us, 99), "late_commands": late_commands})
        return out


def deadline_verdict(timing: Timing, max_missed_fraction: float, fault_step: int) -> dict:
    """The summary fields of a real-time run's deadline verdict: exceeded when the missed deadlines are
    more than ``max_missed_fraction`` of the steps run; and how many were missed from the fault's step
    on (where the TCU's strategy does its identification work)."""
    steps = len(timing.period_us)
    return {"max_missed_fraction": max_missed_fraction,
            "deadlines_exceeded": steps > 0 and timing.missed > max_missed_fraction * steps,
            "missed_deadlines_after_fault": sum(1 for k in timing.missed_steps if k >= fault_step)}


def check_deadlines(summary: dict) -> None:
    """``DeadlinesMissed`` (one line: how many of how many, and the limit) when the summary of a
    real-time run says its missed deadlines exceeded ``max_missed_fraction``; nothing otherwise.
    When most of them fall after the fault, the line says so and names the strategy: its
    identification work there, not the bus, is then what overran the period."""
    if summary.get("deadlines_exceeded"):
        missed, steps, limit = summary["missed_deadlines"], summary["steps"], summary["max_missed_fraction"]
        after = summary.get("missed_deadlines_after_fault")
        where = ""
        if after is not None and 2 * after > missed:
            where = (f"; {after} of them after the fault at {summary.get('t_fault_s', math.nan):g} s, while the TCU's "
                     f"strategy {summary.get('strategy', '?')} identifies (its work there took longer than a period)")
        raise DeadlinesMissed(f"{missed} of {steps} deadlines missed ({100.0 * missed / steps:.2f} %), more than "
                              f"[bus] max_missed_fraction = {limit:g} allows{where}; logs written")


def exchange(node: PlantNode, steps: int, mode: str, bar: Progress | None = None) -> Timing:
    """The loop: ``steps`` exchange periods of sense -> send -> await the command -> apply."""
    period = node.period_s
    realtime = mode == "realtime"
    deadline_fraction = node.settings.deadline_fraction
    timing = Timing(period, mode, deadline_fraction)
    with collector_paused(realtime):
        t0 = timing.t0_s = time.perf_counter() + 0.005
        prev = None
        for k in range(steps):
            if realtime:
                t_k = t0 + k * period
                while time.perf_counter() < t_k:          # handle frames until the period starts
                    node.poll(t_k)
                deadline = t_k + deadline_fraction * period
            else:
                t_k = deadline = None
            start = time.perf_counter()
            node.send_sensor()
            command = node.await_command(k, deadline)
            missed = command is None
            if missed:
                timing.missed_steps.append(k)
                timing.round_trip_us.append(math.nan)
                command = TorqueCommand(k, node.rig.plant.state.torque_nm)    # hold the torque being applied
            else:
                timing.round_trip_us.append((time.perf_counter() - start) * 1e6)
            node.rig.apply(command)
            lateness = (start - t_k) * 1e6 if realtime else 0.0
            period_us = math.nan if prev is None else (start - prev) * 1e6
            prev = start
            timing.period_us.append(period_us)
            timing.lateness_us.append(lateness)
            if node.rec:
                write_timing(node.rec, k, k * period, period_us, timing.round_trip_us[-1], lateness, missed)
            if bar is not None and k % 200 == 0:
                bar.update(k)
        node.awaited = steps
    return timing


def run(scenario, strategy: str = DEFAULT_STRATEGY, seed: int | None = None, *, bus: str = "auto", mode: str = "lockstep",
        external_tcu: bool = False, out_dir=None, record: bool = True, progress: bool | None = None,
        set_args=None, plant=None, plant_label: str | None = None, log=None, tcu_process=None) -> dict:
    """One HIL run; returns the summary (``hil run --json``).

    ``bus="inprocess"``: the TCU node answers in this thread; otherwise it is a child process on the
    bus, or (``external_tcu``) a TCU already there.  A TCU process is handed ``scenario`` itself, overrides
    and all (``Scenario.handover``), and a TCU that announces another scenario's digest is refused before
    the first period (``ScenarioMismatch``); ``set_args`` is accepted for older callers and not read.
    ``tcu_process``: with ``external_tcu``, the TCU's process (a ``Popen``; its ``stderr_path`` attribute,
    when set, names the file its stderr goes to) when the caller started it: watched as the run's own
    child, so an exit before it joins is ``TcuDidNotStart`` and a death mid-run ``PeerSilent``, each
    within milliseconds and with its exit code and last stderr lines.  ``plant``: a plant object
    instead of the CasADi model (see ``hil.plants``; the caller closes it), named ``plant_label`` in the
    summary and the log's name.  Raises ``BusError`` for a bus that cannot be used, ``PeerSilent``
    (with ``.summary``) when the TCU falls silent or dies, ``KeyboardInterrupt`` on Ctrl-C or SIGTERM;
    the log is closed in every case (``hil.session``).
    """
    with Session(scenario, strategy, seed, bus=bus, mode=mode, external_tcu=external_tcu, out_dir=out_dir,
                 record=record, set_args=set_args, plant=plant, plant_label=plant_label, log=log,
                 tcu_process=tcu_process) as session:
        scenario = session.scenario
        bar = Progress(scenario.steps, f"{scenario.name} {strategy} {session.tcu.handle.name} {mode}", progress)
        wall0 = time.perf_counter()
        try:
            timing = exchange(session.node, scenario.steps, mode, bar)
        finally:
            bar.close()
        wall = time.perf_counter() - wall0
        verdict = (deadline_verdict(timing, scenario.bus.max_missed_fraction,
                                    round(scenario.run.fault_time_s / scenario.run.exchange_period_s))
                   if mode == "realtime" else None)
        return session.finish(timing, wall, verdict)
