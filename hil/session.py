"""The session of one HIL run: everything the run holds around the exchange loop (``hil.exchange``),
taken in order and given back in reverse on every path, and the fault recorded once.

``Session`` holds its resources as context managers on one ``contextlib.ExitStack``; in the order
taken (and released in reverse):

1. the interrupt guard (``interrupts_between_writes``): SIGINT and SIGTERM end the run as
   ``KeyboardInterrupt``, never mid-write;
2. the TCU's report directory (a TCU process of this run writes its counters there) and the frame
   key's directory (``authenticate``);
3. real time: the CPU latency request (``hil.rt.cpu_latency``);
4. this process on the plant's CPUs (``node_cpus``), the old affinity restored after (a bench runs
   one run after another in one process);
5. real time: SCHED_FIFO (``[bus] rt_priority``), the old policy restored after;
6. real time: the idle spinners (``hil.rt.idle_spin``);
7. the bus and the TCU on it (``Tcu``), the TCU process stopped and the bus closed after;
8. the log (``start_recording``), closed with the summary; without one (the run failed) with a
   "run aborted" event; closed as far as the disk allows when writing failed;
9. the failure path, written once (``_record_fault``): on any exception the TCU is told the plant
   failed (fault heartbeats), and the log gets the fault: an interrupt's event, a ``PeerSilent``'s
   event, ``fault`` metadata and partial summary (``e.summary``), a diverged plant's event
   (``FloatingPointError``, raised on as ``PlantError``); nothing more for a log that cannot be
   written (``LogWriteError``).

A resource that fails to open (a bus that cannot be used, a full disk) releases those taken before
it.  A step of the host's tuning that is refused (pinning, SCHED_FIFO, the latency request, the
spinners) is said in one line through ``log`` and the run goes on without it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .bus.frames import DBC_PATH, STATE_FAULT, STATE_FINISHED, FrameCodec, bus_load, format_bus_load
from .bus.mapping import codec_for, mapped_bus_load
from .bus.link import MODES, GuardedBus, die_with_parent, open_bus, resolve
from .bus.secoc import AUTO_AUTH_BUSES, node_key, write_key
from .effects import TRUTH_KEY
from .errors import BusError, ConfigError, HilError, LogWriteError, PeerSilent, PlantError
from .log.record import interrupts_between_writes, log_path, prepare_out_dir, start_recording, write_control_metrics
from .plant_node import PlantNode, PlantRig
from .rt.cpu_latency import CpuLatencyRequest
from .rt.idle_spin import SPIN, IdleSpinners, idle_mode
from .tcu_node import TcuNode, set_cpu_affinity
from .trace import Trace, clean

LOAD_WARN_PERCENT = 70.0
#: the log rows a run may hold back for writing (what a SIGKILL can lose beyond the unfinished chunk)
RECORD_QUEUE_S, ROWS_PER_PERIOD = 0.5, 10
CHILD_EXIT_TIMEOUT_S = 20.0
TRANSPORTS = ("inprocess", "process", "external")


def log_writer(mode: str, transport: str, cpus: int | None = None) -> str:
    """Where a run's log rows are encoded (``Recorder.defer``): in a writer process of their own,
    unless two lockstep nodes poll on a machine of two CPUs or fewer, where a third busy process can
    only take its CPU from them (the plant then writes while it waits for the TCU;
    ``docs/design/session.md`` gives the measurement behind the rule)."""
    cpus = cpus or os.cpu_count() or 1
    return "inline" if mode == "lockstep" and transport != "inprocess" and cpus <= 2 else "process"


def node_cpus(settings, mode: str, transport: str) -> tuple[tuple, tuple]:
    """(plant CPUs, TCU CPUs) of a run: ``[bus] cpu_affinity_plant`` / ``cpu_affinity_tcu`` as set;
    in lockstep with a TCU process of this run, neither set and ``[bus] lockstep_pin`` on, the first
    two CPUs this process may use, one each.  Why: two lockstep nodes poll the bus in turns
    (``lockstep_spin_s``), and the kernel wakes a node on the CPU of the node that woke it; where
    both land on one CPU while a third process holds the other, one spins on the CPU the other needs
    (``docs/design/session.md`` gives the measurement, taken with this setting on and off)."""
    plant, tcu = tuple(settings.cpu_affinity_plant), tuple(settings.cpu_affinity_tcu)
    if plant or tcu or mode != "lockstep" or transport != "process" or not settings.lockstep_pin:
        return plant, tcu
    try:
        allowed = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity API (not Linux): left unpinned
        return plant, tcu
    if len(allowed) < 2:
        return plant, tcu
    return (allowed[0],), (allowed[1],)


def authenticate(scenario, bus: str, transport: str, key_dir, log) -> tuple[object, list[str]]:
    """The scenario with its ``[bus] auth`` resolved for this run (``hil/bus/secoc.py``), and the ``--set``
    items that give the TCU process the same: ``auto`` is on for the buses only this user's processes
    can reach (``AUTO_AUTH_BUSES``) and off for the others, ``inprocess`` among them (no other node);
    on, without a key file, a new key is written in ``key_dir`` (readable by this user only).
    An external TCU cannot be handed a key: ``auto`` is off there (with a warning), ``on`` needs the
    key file both sides read."""
    settings = scenario.bus
    mode = settings.auth
    if settings.dbc:         # a TCU's own DBC has no authentication trailer ("on" is refused at load)
        mode = "off"
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


# -- the resources, one context manager each ----------------------------------------------------------
def temporary_directory(prefix: str, what: str) -> tempfile.TemporaryDirectory:
    """A private temporary directory (a context manager giving its name), removed at exit;
    ``LogWriteError`` naming ``what`` it was for when it cannot be made."""
    try:
        return tempfile.TemporaryDirectory(prefix=prefix)
    except OSError as e:     # a full disk: tempfile cannot even probe a directory
        raise LogWriteError(f"cannot create a temporary directory for {what}: {e.strerror or e}") from None


@contextlib.contextmanager
def pinned(cpus, log):
    """This process on the CPU numbers ``cpus`` inside (nothing when empty; a refusal said through
    ``log``, ``set_cpu_affinity``), then back on the CPUs it had."""
    old = os.sched_getaffinity(0) if cpus and hasattr(os, "sched_getaffinity") else None
    if not set_cpu_affinity(cpus, "plant", log):
        old = None
    try:
        yield
    finally:
        if old is not None:
            with contextlib.suppress(OSError):
                os.sched_setaffinity(0, old)


@contextlib.contextmanager
def fifo_priority(priority: int, log):
    """SCHED_FIFO at ``priority`` for this process inside (the hub and TCU processes started meanwhile
    inherit it; 0: nothing), then its old policy; yields whether it was set (a refusal is said
    through ``log`` and the run goes on at normal priority)."""
    old = None
    if priority > 0:
        try:
            old = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            log(f"realtime: SCHED_FIFO priority {priority}")
        except (AttributeError, PermissionError, OSError) as e:
            log(f"warning: cannot set SCHED_FIFO priority {priority} ({e}); running at normal priority")
            old = None
    try:
        yield old is not None
    finally:
        if old is not None:
            os.sched_setscheduler(0, *old)


@contextlib.contextmanager
def idle_spinners(settings, cpus, log):
    """The run's idle spinners on ``cpus`` inside (``hil.rt.idle_spin``), killed at exit (their
    report is taken before, by ``IdleSpinners.stop``); None, said in one line, when they cannot be
    started."""
    try:
        spinners = IdleSpinners(cpus, rest_s=settings.idle_spin_rest_ms * 1e-3).start()
    except (HilError, OSError) as e:
        log(f"realtime: warning: no idle spinners ({e}); idle CPUs may halt and wake late")
        spinners = None
    else:
        log(f"realtime: a SCHED_IDLE spinner on each of CPUs {','.join(map(str, spinners.cpus))} for the run, "
            f"resting {settings.idle_spin_rest_ms:g} ms every 100 ms: idle CPUs spin instead of halting")
    try:
        yield spinners
    finally:
        if spinners is not None:
            spinners.kill()


class Tcu:
    """The other end of the bus, by transport: ``inprocess`` (a ``TcuNode`` in this thread behind
    ``InprocessTcuBus``), ``process`` (``python -m hil.tcu_node`` as a child, which writes its report
    to ``report_path``) or ``external`` (one already on the bus).  A context manager: ``open`` opens
    the bus and starts what this run starts; ``finish`` collects what only the TCU knows after the
    run; ``close`` (at exit) stops the child and closes the bus."""

    def __init__(self, transport: str, report_path: Path | None = None):
        self.transport = transport
        self.report_path = report_path
        self.node: TcuNode | None = None
        self.child: subprocess.Popen | None = None
        self.handle = None

    def open(self, scenario, strategy, seed, bus: str, mode: str, session_items) -> None:
        """``session_items``: the ``--set`` items of this run's plumbing the child process gets beside the
        scenario's hand-over (its frame key, its CPUs: ``hil.config.SESSION_BUS_KEYS``)."""
        if self.transport == "inprocess":
            self.node = TcuNode(scenario, strategy, seed, realtime=mode == "realtime")
            self.handle = open_bus("inprocess", inprocess_node=self.node)
            return
        self.handle = open_bus(bus)
        if self.transport == "external":
            if self.handle.hub is not None:
                raise BusError("bus hub: a hub started here has no external TCU on it; start one with "
                               "python -m can_remote and give both sides --bus remote:ws://127.0.0.1:PORT/")
            if self.handle.name == "udp_multicast":       # a group drawn for this run: no TCU knows it
                raise BusError("bus udp_multicast: a group drawn for this run has no external TCU on it; give "
                               "both sides one group, --bus udp_multicast:GROUP:PORT (e.g. "
                               "udp_multicast:239.255.42.17:43117)")
            return
        if self.handle.peer_spec is None:
            raise BusError(f"bus {self.handle.name}: reachable only inside this process; a TCU process cannot "
                           "join it (use inprocess, hub or socketcan:<ch>)")
        # the child runs the scenario this run resolved, overrides and all, never the file again
        handover = self.report_path.with_name("scenario.json")
        try:
            handover.write_text(json.dumps(scenario.handover()))
        except (OSError, TypeError, ValueError) as e:
            raise ConfigError(f"{scenario.path}: cannot hand the scenario to the TCU process: {e}") from None
        cmd = [sys.executable, "-m", "hil.tcu_node", "--handover", str(handover), "--bus", self.handle.peer_spec,
               "--strategy", strategy, "--seed", str(seed), "--mode", mode, "--report", str(self.report_path)]
        for item in session_items or []:
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
        except (OSError, ValueError):  # no report (the TCU died before writing it): its exit code is judged below
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
        except subprocess.TimeoutExpired:  # a TCU that ignores SIGTERM is killed
            child.kill()
            child.wait()

    def close(self) -> None:
        self.stop_child()
        if self.handle is not None:
            self.handle.close()

    def __enter__(self) -> "Tcu":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


def _tcu_counters(report: dict | None) -> dict:
    """What only the TCU knows (None for an external TCU)."""
    report = report or {}
    return {"tcu_rejected_frames": report.get("rejected_frames"), "tcu_rejected_readings": report.get("rejected_readings"),
            "tcu_events": report.get("events"), "tcu_stale_skipped": report.get("stale_skipped"),
            "tcu_resent": report.get("resent"), "tcu_rearms": report.get("rearms")}


def _recorded(summary: dict | None) -> dict | None:
    """The summary as the log keeps it: a real run's effects stay under the truth key alone
    (``hil.effects.TRUTH_KEY``), which ``hil gap`` never reads."""
    if summary is None or not summary.get("reality"):
        return summary
    return {**summary, "reality": f"effects under the {TRUTH_KEY!r} metadata"}


def _log_path(scenario, strategy, seed, out_dir, plant_label) -> Path:
    """The run's log path, its directory made (a bad ``--out`` fails here, before anything starts)."""
    return log_path(scenario, strategy, seed, prepare_out_dir(out_dir), plant_label, scenario.extra.get("reality"))


# -- the session ----------------------------------------------------------------------------------------
class Session:
    """``with Session(scenario, ...) as s:`` the run's resources (module docstring), its plant node
    ``s.node`` on the bus with the TCU there; the exchange loop runs inside and hands its ``Timing``
    to ``finish``, which makes the summary the log closes with.  The arguments are ``hil.exchange.run``'s.
    Raises ``BusError`` for an unknown mode or a bus that cannot be used."""

    def __init__(self, scenario, strategy: str, seed: int | None, *, bus: str, mode: str, external_tcu: bool,
                 out_dir, record: bool, set_args, plant, plant_label: str | None, log, tcu_process=None):
        if mode not in MODES:
            raise BusError(f"unknown mode {mode!r}; available: {', '.join(MODES)}")
        self.log = log or (lambda text: print(text, file=sys.stderr))
        self.scenario, self.strategy, self.bus, self.mode = scenario, strategy, bus, mode
        self.seed = scenario.run.seed if seed is None else seed
        self.record, self.plant, self.plant_label = record, plant, plant_label
        # the scenario reaches a TCU process whole (Tcu.open's hand-over); ``set_args`` is kept for callers
        # that still pass it and is not read.  What the child gets beside: this run's plumbing items
        self.session_items: list[str] = []
        self.out_dir = out_dir
        self.transport = "inprocess" if bus == "inprocess" else ("external" if external_tcu else "process")
        self.tcu_process = tcu_process if self.transport == "external" else None   # watched as our own child
        self.tcu: Tcu | None = None
        self.path: Path | None = None
        self.trace: Trace | None = None
        self.latency: CpuLatencyRequest | None = None
        self.spinners: IdleSpinners | None = None
        self.idle: str | None = None
        self.mapping = None
        self.load: dict | None = None
        self.rec = self.node = self.timing = self.summary = None
        self.wall_s = 0.0
        self._ready_s: float | None = None       # time.perf_counter() when the session was open
        self._stack: contextlib.ExitStack | None = None

    def __enter__(self) -> "Session":
        with contextlib.ExitStack() as stack:      # a failure on the way releases what was taken
            self._open(stack)
            self._stack = stack.pop_all()
        self._ready_s = time.perf_counter()
        return self

    def __exit__(self, *exc) -> bool:
        stack, self._stack = self._stack, None
        return stack.__exit__(*exc)

    def _open(self, stack: contextlib.ExitStack) -> None:
        scenario, mode, log = self.scenario, self.mode, self.log
        settings = scenario.bus
        period = scenario.run.exchange_period_s
        self.mapping = codec_for(scenario).mapping if settings.dbc else None
        # a mapped DBC's bit rates (Baudrate, a CAN FD data rate) are the bus's; [bus] bitrate/data_bitrate where
        # it names none
        dbc_rate, dbc_data_rate = self.mapping.bitrates if self.mapping is not None else (None, None)
        bitrate, data_bitrate = dbc_rate or settings.bitrate, dbc_data_rate or settings.data_bitrate
        self.load = bus_load(FrameCodec(period).db, period, settings.heartbeat_period_s, bitrate, data_bitrate)
        if self.mapping is not None:      # the mapped frames on a classical bus; the HIL frames beside them
            self.load["mapped_load_percent"] = mapped_bus_load(self.mapping, period, bitrate)
            self.load["bitrate_from"] = Path(self.mapping.dbc_path).name if dbc_rate else "[bus] bitrate"
        if self.record:
            # an external TCU's strategy is its own: its log is named <scenario>-external-<seed>
            named = "external" if self.transport == "external" else self.strategy
            self.path = _log_path(scenario, named, self.seed, self.out_dir, self.plant_label)
        stack.enter_context(interrupts_between_writes())   # SIGTERM ends a run like Ctrl-C, never mid-write
        report_dir = (stack.enter_context(temporary_directory("hil-tcu-", "the TCU's report"))
                      if self.transport == "process" else None)
        key_dir = stack.enter_context(temporary_directory("hil-key-", "the frame key"))
        self.tcu = Tcu(self.transport, Path(report_dir) / "report.json" if report_dir else None)
        scenario, auth_items = authenticate(scenario, self.bus, self.transport, key_dir, log)
        self.scenario = scenario
        settings = scenario.bus                 # as resolved: the log's bus metadata says auth on/off
        self.session_items += auth_items
        self.trace = Trace(scenario)
        realtime = mode == "realtime"
        self.latency = stack.enter_context(contextlib.closing(
            CpuLatencyRequest(settings.cpu_latency_us if realtime else -1, log)))
        every_cpu = sorted(os.sched_getaffinity(0))       # the idle spinners' CPUs, read before this process is pinned
        plant_cpus, tcu_cpus = node_cpus(settings, mode, self.transport)
        if tcu_cpus != settings.cpu_affinity_tcu:
            self.session_items.append(f"bus.cpu_affinity_tcu={list(tcu_cpus)}")
        stack.enter_context(pinned(plant_cpus, log))
        fifo = stack.enter_context(fifo_priority(settings.rt_priority if realtime else 0, log))
        latency = self.latency
        self.idle = idle_mode(settings.idle_spin, latency.held_us, latency.driver, fifo=fifo) if realtime else None
        if self.idle == SPIN:
            self.spinners = stack.enter_context(idle_spinners(settings, every_cpu, log))
            if self.spinners is None:
                self.idle = idle_mode("off", latency.held_us, latency.driver, fifo=fifo)
        tcu = stack.enter_context(self.tcu)
        stack.push(self._close_log)          # the log, once started, closes after the fault is in it ...
        stack.push(self._record_fault)       # ... and before the TCU is stopped and the bus closed
        tcu.open(scenario, self.strategy, self.seed, self.bus, mode, self.session_items)
        self._start_log()
        self.node = PlantNode(PlantRig(scenario, self.seed, self.trace, self.rec, plant=self.plant),
                              GuardedBus(tcu.handle.bus, tcu.handle.name), mode,
                              strategy=self.strategy, watch=tcu.child or self.tcu_process,
                              watch_silence=tcu.node is None)
        if tcu.node is None:
            self.node.wait_for_tcu()
        self.node.begin()

    def _start_log(self) -> None:
        """The bus's load and warnings said; the log started (``record``), its rows deferred."""
        scenario, settings, load, handle, log = self.scenario, self.scenario.bus, self.load, self.tcu.handle, self.log
        if self.mapping is not None:
            log(f"mapped bus ({Path(self.mapping.dbc_path).name}): its frames load a classical bus at "
                f"{load['bitrate'] / 1e3:g} kbit/s ({load['bitrate_from']}) to {load['mapped_load_percent']:.1f} %; "
                "no step counters, "
                "not authenticated")
        log(format_bus_load(load) + f" on {handle.name}")
        if handle.hub is not None:
            log(f"warning: bus hub: any process of any user on this machine can join it ({handle.hub.url}); "
                f"frames are {'authenticated' if settings.auth == 'on' else 'not authenticated'} "
                "(the embedded local bus is the default for a reason)")
        if handle.extra.get("open_to"):           # udp_multicast (hil/bus/multicast.py)
            log(f"warning: bus {handle.name}: {handle.extra['open_to']}; frames are "
                f"{'authenticated' if settings.auth == 'on' else 'not authenticated'}")
        if load["load_percent"] > LOAD_WARN_PERCENT:
            log(f"warning: bus load {load['load_percent']:.1f} % is above {LOAD_WARN_PERCENT:g} % "
                f"(raise [bus] bitrate/data_bitrate or the exchange period)")
        if not self.record:
            return
        if self.path.exists():        # said when it happens: a run that fails before this leaves the old log
            log(f"warning: replacing {self.path}\n  (a log of an earlier run with the same scenario, strategy, "
                "seed, plant and effects)")
        plant = self.plant
        dbc_path = Path(self.mapping.dbc_path) if self.mapping is not None else DBC_PATH
        dbc = {"name": dbc_path.name, "text": dbc_path.read_text()}     # the checks decode frames with it
        self.rec = start_recording(
            scenario, self.strategy, self.seed, handle.name, self.mode, self.path,
            plant_meta=plant.metadata() if hasattr(plant, "metadata") else None,
            dbc=dbc,
            bus_meta={"spec": self.bus, "name": handle.name, "dbc": dbc["name"], "transport": self.transport,
                      **{k: repr(v) for k, v in dataclasses.asdict(settings).items()},
                      "load_percent": f"{load['load_percent']:.2f}"})
        # rows are written while the plant waits for the TCU (Recorder.defer)
        period = scenario.run.exchange_period_s
        self.rec.defer(max(int(RECORD_QUEUE_S / period) * ROWS_PER_PERIOD, 1000),
                       block_when_full=self.mode == "lockstep", writer=log_writer(self.mode, self.transport))

    def summarise(self, extra: dict) -> dict:
        """The run's summary (``hil run --json``) from its ``Trace``, node, timing and resources."""
        node, timing, wall, tcu, load = self.node, self.timing, self.wall_s, self.tcu, self.load
        return clean(self.trace.summary(
            strategy=self.strategy, seed=self.seed, bus=tcu.handle.name if tcu.handle else self.bus,
            mcap_path=self.path,
            extra={"mode": self.mode, "transport": tcu.transport, "plant": self.plant_label or "casadi",
                   "reality": self.scenario.extra.get("reality") or None, "wall_s": wall,
                   "sim_s": node.t_s if node else 0.0, "sim_s_per_wall_s": node.t_s / wall if node and wall else None,
                   "bus_load_percent": load["load_percent"], "bus_bitrate": load["bitrate"],
                   "mapped_bus_load_percent": load.get("mapped_load_percent"),
                   "frame_auth": self.scenario.bus.auth, "cpu_latency_us": self.latency.held_us, "idle_cpus": self.idle,
                   **(node.counters() if node else {}),
                   **(timing.summary(node.late_commands) if timing else {}),
                   "control": "external" if tcu.transport == "external" else self.scenario.control.law,
                   **(node.rig.truth.metrics(self.trace.events, self.trace.estimates or None) if node else {}), **extra}))

    def finish(self, timing, wall_s: float, verdict: dict | None = None) -> dict:
        """After the loop (its ``Timing`` and wall seconds): the TCU told the run is over and its last
        frames and counters collected, the spinners' report taken, and the summary, with ``verdict``
        (the loop's deadline fields) and the log's counts, which the log closes with."""
        self.timing, self.wall_s = timing, wall_s
        node, settings = self.node, self.scenario.bus
        node.finish(STATE_FINISHED)
        away = {}
        if self.spinners is not None:
            try:
                self.spinners.stop()
                away = self.spinners.summary(timing.missed_steps, timing.t0_s, node.period_s,
                                             settings.deadline_fraction)
            except HilError as e:       # the run stands; only its CPU absences are unknown
                self.log(f"realtime: warning: {e}; the time CPUs were away is unknown")
        summary = self.summary = self.summarise({**self.tcu.finish(node), **away})
        summary.update(verdict or {})
        if self.rec:
            write_control_metrics(self.rec, node.t_s, summary["control"], summary)
            summary["messages"] = self.rec.messages + 1      # + the summary itself
            summary["log_rows_dropped"] = self.rec.overflow  # real time: rows the full queue could not take
        return summary

    def _record_fault(self, kind, e, tb) -> bool:
        """Exit callback, the failure path (module docstring, 9)."""
        if e is None:
            return False
        node, rec = self.node, self.rec
        if rec and node is not None:
            if isinstance(e, KeyboardInterrupt):
                rec.event(node.t_s, "ERROR", "run interrupted (SIGINT/SIGTERM)")   # one write: already atomic
            elif isinstance(e, (PeerSilent, FloatingPointError)):
                rec.event(node.t_s, "ERROR", f"fault: {e}")
            if isinstance(e, PeerSilent):
                rec.metadata("fault", {"reason": str(e), "step": str(node.awaited), "t_s": repr(node.t_s)})
        if node is not None:
            node.finish(STATE_FAULT)     # the TCU ends too (after a LogWriteError: the log closes as far as it can)
        if isinstance(e, PeerSilent):
            if not self.wall_s and self._ready_s is not None:     # the loop did not finish: wall up to the fault
                self.wall_s = time.perf_counter() - self._ready_s
            e.summary = self.summarise({"fault": str(e)})
        if isinstance(e, FloatingPointError):    # the plant diverged: a scenario or --reality value out of range
            raise PlantError(f"{self.scenario.path}: {e} (a value of the scenario or of --reality beyond what the "
                             "physics can integrate?)") from None
        return False

    def _close_log(self, *exc) -> bool:
        """Exit callback: the log closed with the summary (none: the run failed), a result whose status
        never came still logged, the reality's truth recorded; a log that cannot be closed leaves the
        callbacks after this one (the TCU stopped, the bus closed) to run."""
        rec, node = self.rec, self.node
        if rec:
            with rec.atomic():
                if node is not None:
                    node.settle_results()
                    if self.summary is None:
                        rec.event(node.t_s, "ERROR", "run aborted")
                    node.rig.reality.record_truth(rec)
                rec.close(_recorded(self.summary))
        return False
