"""The exchange loop: the ONLY plant-side loop of a HIL run, and ``run`` that wires it up.

Per exchange period k the plant node senses, sends ``PlantSensor(k)`` and waits for ``TorqueCommand(k)``:

- ``lockstep``: it waits as long as the TCU needs (deterministic; as fast as the bus allows);
- ``realtime``: period k starts at ``t0 + k * period`` of the wall clock; the command must arrive
  before ``deadline_fraction`` of the period, otherwise the deadline is missed and the torque being
  applied is held.  Period jitter, lateness, round trip and misses go to ``/loop/timing``.

The TCU on the other end is reached through one of three transports, chosen by ``run``:

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
import dataclasses
import gc
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from identifier import DEFAULT_STRATEGY
from identifier.messages import TorqueCommand

from .rt.cpu_latency import CpuLatencyRequest
from .rt.idle_spin import SPIN, IdleSpinners, idle_mode
from .effects import TRUTH_KEY
from .errors import BusError, ConfigError, DeadlinesMissed, HilError, LogWriteError, PeerSilent, PlantError
from .bus.frames import DBC_PATH, STATE_FAULT, STATE_FINISHED, FrameCodec, bus_load, format_bus_load
from .bus.link import MODES, GuardedBus, die_with_parent, open_bus, resolve
from .plant_node import PlantNode, PlantRig
from .progress import Progress
from .bus.secoc import AUTO_AUTH_BUSES, node_key, write_key
from .log.record import interrupts_between_writes, log_path, prepare_out_dir, start_recording, write_timing
from .tcu_node import TcuNode, set_cpu_affinity
from .trace import Trace, clean

LOAD_WARN_PERCENT = 70.0
#: the log rows a run may hold back for writing (what a SIGKILL can lose beyond the unfinished chunk)
RECORD_QUEUE_S, ROWS_PER_PERIOD = 0.5, 10
CHILD_EXIT_TIMEOUT_S = 20.0


def log_writer(mode: str, transport: str, cpus: int | None = None) -> str:
    """Where a run's log rows are encoded (``Recorder.defer``): in a writer process of their own,
    unless two lockstep nodes poll on a machine of two CPUs or fewer, where a third busy process can
    only take its CPU from them (the plant then writes while it waits for the TCU; the README gives
    the measurement behind the rule)."""
    cpus = cpus or os.cpu_count() or 1
    return "inline" if mode == "lockstep" and transport != "inprocess" and cpus <= 2 else "process"

TRANSPORTS = ("inprocess", "process", "external")


def node_cpus(settings, mode: str, transport: str) -> tuple[tuple, tuple]:
    """(plant CPUs, TCU CPUs) of a run: ``[bus] cpu_affinity_plant`` / ``cpu_affinity_tcu`` as set;
    in lockstep with a TCU process of this run, neither set and ``[bus] lockstep_pin`` on, the first
    two CPUs this process may use, one each.  Why: two lockstep nodes poll the bus in turns
    (``lockstep_spin_s``), and the kernel wakes a node on the CPU of the node that woke it; where
    both land on one CPU while a third process holds the other, one spins on the CPU the other needs
    (the README gives the measurement, taken with this setting on and off)."""
    plant, tcu = tuple(settings.cpu_affinity_plant), tuple(settings.cpu_affinity_tcu)
    if plant or tcu or mode != "lockstep" or transport != "process" or not settings.lockstep_pin:
        return plant, tcu
    try:
        allowed = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return plant, tcu
    if len(allowed) < 2:
        return plant, tcu
    return (allowed[0],), (allowed[1],)


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


# -- wiring ------------------------------------------------------------------------------------------
class Tcu:
    """The other end of the bus, by transport: ``inprocess`` (a ``TcuNode`` in this thread behind
    ``InprocessTcuBus``), ``process`` (``python -m hil.tcu_node`` as a child) or ``external`` (one
    already on the bus).  ``open`` opens the bus and starts what this run starts; ``finish`` collects
    what only the TCU knows after the run; ``close`` stops the child and closes the bus."""

    def __init__(self, transport: str):
        self.transport = transport
        self.node: TcuNode | None = None
        self.child: subprocess.Popen | None = None
        self.handle = None
        try:
            self._report_dir = tempfile.TemporaryDirectory(prefix="hil-tcu-") if transport == "process" else None
        except OSError as e:     # a full disk: tempfile cannot even probe a directory
            raise LogWriteError(f"cannot create a temporary directory for the TCU's report: {e.strerror or e}") \
                from None
        self.report_path = Path(self._report_dir.name) / "report.json" if self._report_dir else None

    def open(self, scenario, strategy, seed, bus: str, mode: str, set_args) -> None:
        if self.transport == "inprocess":
            self.node = TcuNode(scenario, strategy, seed, realtime=mode == "realtime")
            self.handle = open_bus("inprocess", inprocess_node=self.node)
            return
        self.handle = open_bus(bus)
        if self.transport == "external":
            if self.handle.hub is not None:
                raise BusError("bus hub: a hub started here has no external TCU on it; start one with "
                               "python -m can_remote and give both sides --bus remote:ws://127.0.0.1:PORT/")
            return
        if self.handle.peer_spec is None:
            raise BusError(f"bus {self.handle.name}: reachable only inside this process; a TCU process cannot "
                           "join it (use inprocess, hub or socketcan:<ch>)")
        cmd = [sys.executable, "-m", "hil.tcu_node", str(scenario.path), "--bus", self.handle.peer_spec,
               "--strategy", strategy, "--seed", str(seed), "--mode", mode, "--report", str(self.report_path)]
        for item in set_args or []:
            cmd += ["--set", item]
        self.child = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                      start_new_session=True, preexec_fn=die_with_parent,
                                      env={**os.environ, "PYTHONUNBUFFERED": "1"})

    def finish(self, node: PlantNode) -> dict:
        """After the last period: the TCU's last frames recorded, its counters (None for an external
        TCU); ``PeerSilent`` when its process does not end, or ends with an error."""
        if self.node is not None:
            node.drain()
            return _tcu_counters(self.node.report())
        if self.child is None:
            node.drain_until(lambda: False, 0.2)     # the external TCU's last status and heartbeat
            return _tcu_counters(None)
        node.drain_until(lambda: self.child.poll() is not None, CHILD_EXIT_TIMEOUT_S)
        if self.child.poll() is None:
            self.stop_child()
            raise PeerSilent(f"TCU process did not end within {CHILD_EXIT_TIMEOUT_S:g} s after the run")
        try:
            report = json.loads(self.report_path.read_text())
        except (OSError, ValueError):
            report = {}
        if self.child.returncode != 0:
            raise PeerSilent(f"TCU process ended with code {self.child.returncode} after the run: "
                             f"{report.get('error') or 'no report'}")
        return _tcu_counters(report)

    def stop_child(self) -> None:
        child = self.child
        if child is None or child.poll() is not None:
            return
        child.terminate()
        try:
            child.wait(5)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()

    def close(self) -> None:
        self.stop_child()
        if self.handle is not None:
            self.handle.close()
        if self._report_dir is not None:
            self._report_dir.cleanup()


def _tcu_counters(report: dict | None) -> dict:
    """What only the TCU knows (None for an external TCU)."""
    report = report or {}
    return {"tcu_rejected_frames": report.get("rejected_frames"), "tcu_rejected_readings": report.get("rejected_readings"),
            "tcu_events": report.get("events"), "tcu_stale_skipped": report.get("stale_skipped"),
            "tcu_resent": report.get("resent")}


def _set_rt_priority(priority: int, log):
    """SCHED_FIFO for this process (the hub and TCU processes started after it inherit it); the old
    policy, or None when refused."""
    try:
        old = (os.sched_getscheduler(0), os.sched_getparam(0))
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        log(f"realtime: SCHED_FIFO priority {priority}")
        return old
    except (AttributeError, PermissionError, OSError) as e:
        log(f"warning: cannot set SCHED_FIFO priority {priority} ({e}); running at normal priority")
        return None


def _idle_spinners(settings, cpus, log) -> IdleSpinners | None:
    """The run's idle spinners on ``cpus``, started (``hil.rt.idle_spin``); None, said in one line, when
    they cannot be."""
    try:
        spinners = IdleSpinners(cpus, rest_s=settings.idle_spin_rest_ms * 1e-3).start()
    except (HilError, OSError) as e:
        log(f"realtime: warning: no idle spinners ({e}); idle CPUs may halt and wake late")
        return None
    log(f"realtime: a SCHED_IDLE spinner on each of CPUs {','.join(map(str, spinners.cpus))} for the run, resting "
        f"{settings.idle_spin_rest_ms:g} ms every 100 ms: idle CPUs spin instead of halting")
    return spinners


def _recorded(summary: dict | None) -> dict | None:
    """The summary as the log keeps it: a real run's effects stay under the truth key alone
    (``hil.effects.TRUTH_KEY``), which ``hil gap`` never reads."""
    if summary is None or not summary.get("reality"):
        return summary
    return {**summary, "reality": f"effects under the {TRUTH_KEY!r} metadata"}


def _log_path(scenario, strategy, seed, out_dir, plant_label, log) -> Path:
    path = log_path(scenario, strategy, seed, prepare_out_dir(out_dir), plant_label, scenario.extra.get("reality"))
    if path.exists():
        log(f"warning: replacing {path} (a log of an earlier run with the same scenario, strategy, seed, plant "
            "and effects)")
    return path


def authenticate(scenario, bus: str, transport: str, key_dir, log) -> tuple[object, list[str]]:
    """The scenario with its ``[bus] auth`` resolved for this run (``hil/bus/secoc.py``), and the ``--set``
    items that give the TCU process the same: ``auto`` is on for the buses only this user's processes
    can reach (``AUTO_AUTH_BUSES``) and off for the others, ``inprocess`` among them (no other node);
    on, without a key file, a new key is written in ``key_dir`` (readable by this user only).
    An external TCU cannot be handed a key: ``auto`` is off there (with a warning), ``on`` needs the
    key file both sides read."""
    settings = scenario.bus
    mode = settings.auth
    if mode == "auto":
        if transport == "external" and not settings.auth_key_file:
            log("warning: frames are not authenticated (an external TCU: give both sides [bus] auth_key_file "
                "to authenticate)")
            mode = "off"
        else:
            mode = "on" if resolve(bus).split(":")[0] in AUTO_AUTH_BUSES or settings.auth_key_file else "off"
    key_file = settings.auth_key_file
    if mode == "on" and not key_file:
        if transport == "external":
            raise ConfigError("bus.auth = \"on\" with an external TCU needs bus.auth_key_file (the key both sides "
                              "read)")
        key_file = str(write_key(Path(key_dir) / "frames.key"))
    scenario = dataclasses.replace(scenario, bus=dataclasses.replace(settings, auth=mode, auth_key_file=key_file))
    node_key(scenario.bus)                      # a bad key file fails here, before anything starts
    items = [f"bus.auth={json.dumps(mode)}"] + ([f"bus.auth_key_file={json.dumps(key_file)}"] if key_file else [])
    return scenario, items


def run(scenario, strategy: str = DEFAULT_STRATEGY, seed: int | None = None, *, bus: str = "auto", mode: str = "lockstep",
        external_tcu: bool = False, out_dir=None, record: bool = True, progress: bool | None = None,
        set_args=None, plant=None, plant_label: str | None = None, log=None) -> dict:
    """One HIL run; returns the summary (``hil run --json``).

    ``bus="inprocess"``: the TCU node answers in this thread; otherwise it is a child process on the
    bus, or (``external_tcu``) a TCU already there.  ``set_args``: the ``--set`` items that produced
    ``scenario`` (the TCU process loads the scenario again with them).  ``plant``: a plant object
    instead of the CasADi model (see ``hil.plants``; the caller closes it), named ``plant_label`` in the
    summary and the log's name.  Raises ``BusError`` for a bus that cannot be used, ``PeerSilent``
    (with ``.summary``) when the TCU falls silent or dies, ``KeyboardInterrupt`` on Ctrl-C or SIGTERM;
    the log is closed in every case.
    """
    if mode not in MODES:
        raise BusError(f"unknown mode {mode!r}; available: {', '.join(MODES)}")
    log = log or (lambda text: print(text, file=sys.stderr))
    seed = scenario.run.seed if seed is None else seed
    settings = scenario.bus
    period = scenario.run.exchange_period_s
    load = bus_load(FrameCodec(period).db, period, settings.heartbeat_period_s, settings.bitrate,
                    settings.data_bitrate)
    path = _log_path(scenario, strategy, seed, out_dir, plant_label, log) if record else None
    tcu = Tcu("inprocess" if bus == "inprocess" else ("external" if external_tcu else "process"))
    try:
        key_dir = tempfile.TemporaryDirectory(prefix="hil-key-")
    except OSError as e:     # a full disk
        raise LogWriteError(f"cannot create a temporary directory for the frame key: {e.strerror or e}") from None
    scenario, auth_items = authenticate(scenario, bus, tcu.transport, key_dir.name, log)
    settings = scenario.bus                     # as resolved: the log's bus metadata says auth on/off
    set_args = [*(set_args or []), *auth_items]
    trace = Trace(scenario)
    rec = node = timing = summary = None
    wall = 0.0

    def summarise(extra: dict) -> dict:
        return clean(trace.summary(
            strategy=strategy, seed=seed, bus=tcu.handle.name if tcu.handle else bus, mcap_path=path,
            extra={"mode": mode, "transport": tcu.transport, "plant": plant_label or "casadi",
                   "reality": scenario.extra.get("reality") or None, "wall_s": wall,
                   "sim_s": node.t_s if node else 0.0, "sim_s_per_wall_s": node.t_s / wall if node and wall else None,
                   "bus_load_percent": load["load_percent"],
                   "frame_auth": scenario.bus.auth, "cpu_latency_us": latency.held_us, "idle_cpus": idle,
                   **(node.counters() if node else {}),
                   **(timing.summary(node.late_commands) if timing else {}), **extra}))

    latency = CpuLatencyRequest(settings.cpu_latency_us if mode == "realtime" else -1, log)
    every_cpu = sorted(os.sched_getaffinity(0))       # the idle spinners' CPUs, read before this process is pinned
    plant_cpus, tcu_cpus = node_cpus(settings, mode, tcu.transport)
    if tcu_cpus != settings.cpu_affinity_tcu:
        set_args.append(f"bus.cpu_affinity_tcu={list(tcu_cpus)}")
    old_cpus = os.sched_getaffinity(0) if plant_cpus and hasattr(os, "sched_getaffinity") else None
    if not set_cpu_affinity(plant_cpus, "plant", log):
        old_cpus = None
    old_sched = _set_rt_priority(settings.rt_priority, log) if mode == "realtime" and settings.rt_priority > 0 \
        else None
    idle = idle_mode(settings.idle_spin, latency.held_us, latency.driver, fifo=old_sched is not None) \
        if mode == "realtime" else None
    spinners = _idle_spinners(settings, every_cpu, log) if idle == SPIN else None
    if idle == SPIN and spinners is None:
        idle = idle_mode("off", latency.held_us, latency.driver, fifo=old_sched is not None)
    with interrupts_between_writes():   # SIGTERM ends a run like Ctrl-C, never mid-write
        try:
            tcu.open(scenario, strategy, seed, bus, mode, set_args)
            log(format_bus_load(load) + f" on {tcu.handle.name}")
            if tcu.handle.hub is not None:
                log(f"warning: bus hub: any process of any user on this machine can join it ({tcu.handle.hub.url}); "
                    f"frames are {'authenticated' if scenario.bus.auth == 'on' else 'not authenticated'} "
                    "(the embedded local bus is the default for a reason)")
            if load["load_percent"] > LOAD_WARN_PERCENT:
                log(f"warning: bus load {load['load_percent']:.1f} % is above {LOAD_WARN_PERCENT:g} % "
                    f"(raise [bus] bitrate/data_bitrate or the exchange period)")
            if record:
                rec = start_recording(
                    scenario, strategy, seed, tcu.handle.name, mode, path,
                    plant_meta=plant.metadata() if hasattr(plant, "metadata") else None,
                    dbc={"name": DBC_PATH.name, "text": DBC_PATH.read_text()},
                    bus_meta={"spec": bus, "name": tcu.handle.name, "dbc": DBC_PATH.name, "transport": tcu.transport,
                              **{k: repr(v) for k, v in dataclasses.asdict(settings).items()},
                              "load_percent": f"{load['load_percent']:.2f}"})
            if rec:      # rows are written while the plant waits for the TCU (Recorder.defer)
                rec.defer(max(int(RECORD_QUEUE_S / period) * ROWS_PER_PERIOD, 1000), block_when_full=mode == "lockstep",
                          writer=log_writer(mode, tcu.transport))
            node = PlantNode(PlantRig(scenario, seed, trace, rec, plant=plant),
                             GuardedBus(tcu.handle.bus, tcu.handle.name), mode,
                             strategy=strategy, watch=tcu.child, watch_silence=tcu.node is None)
            if tcu.node is None:
                node.wait_for_tcu()
            bar = Progress(scenario.steps, f"{scenario.name} {strategy} {tcu.handle.name} {mode}", progress)
            wall0 = time.perf_counter()
            try:
                timing = exchange(node, scenario.steps, mode, bar)
            finally:
                bar.close()
            wall = time.perf_counter() - wall0
            node.finish(STATE_FINISHED)
            away = {}
            if spinners is not None:
                try:
                    spinners.stop()
                    away = spinners.summary(timing.missed_steps, timing.t0_s, period, settings.deadline_fraction)
                except HilError as e:       # the run stands; only its CPU absences are unknown
                    log(f"realtime: warning: {e}; the time CPUs were away is unknown")
            summary = summarise({**tcu.finish(node), **away})
            if mode == "realtime":
                summary.update(deadline_verdict(timing, settings.max_missed_fraction,
                                                round(scenario.run.fault_time_s / scenario.run.exchange_period_s)))
            if rec:
                summary["messages"] = rec.messages + 1   # + the summary itself
                summary["log_rows_dropped"] = rec.overflow     # real time: rows the full queue could not take
        except PeerSilent as e:
            if rec and node is not None:
                rec.event(node.t_s, "ERROR", f"fault: {e}")
                rec.metadata("fault", {"reason": str(e), "step": str(node.awaited), "t_s": repr(node.t_s)})
            if node is not None:
                node.finish(STATE_FAULT)
            e.summary = summarise({"fault": str(e)})
            raise
        except KeyboardInterrupt:
            if rec and node is not None:
                rec.event(node.t_s, "ERROR", "run interrupted (SIGINT/SIGTERM)")   # one write: already atomic
            if node is not None:
                node.finish(STATE_FAULT)
            raise
        except LogWriteError:
            if node is not None:
                node.finish(STATE_FAULT)     # the TCU ends too; the log is closed as far as the disk allows
            raise
        except FloatingPointError as e:      # the plant diverged: a scenario or --reality value out of range
            if rec and node is not None:
                rec.event(node.t_s, "ERROR", f"fault: {e}")
            if node is not None:
                node.finish(STATE_FAULT)
            raise PlantError(f"{scenario.path}: {e} (a value of the scenario or of --reality beyond what the "
                             "physics can integrate?)") from None
        finally:
            try:
                if rec:
                    with rec.atomic():
                        if node is not None:
                            node.settle_results()        # a result whose status never came is still logged
                        if summary is None and node is not None:
                            rec.event(node.t_s, "ERROR", "run aborted")
                        if node is not None:
                            node.rig.reality.record_truth(rec)
                        rec.close(_recorded(summary))
            finally:                                     # a log that cannot be closed still stops the TCU
                tcu.close()
                key_dir.cleanup()
                if spinners is not None:
                    spinners.kill()
                latency.close()
                if old_sched is not None:
                    os.sched_setscheduler(0, *old_sched)
                if old_cpus is not None:        # a bench runs one run after another in this process
                    with contextlib.suppress(OSError):
                        os.sched_setaffinity(0, old_cpus)
    return summary
