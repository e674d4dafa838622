"""The TCU node: frames in, frames out, around a ``TractionIdentifier``.

``TcuNode.handle(msg)`` turns one received frame into the reply frames (TorqueCommand first, then a
TcuSample per sample the strategy took, a TcuResult per identification event, TcuStatus); replay and
the in-process bus call it directly.  ``serve`` runs a node on an open bus with heartbeats and
plant-silence detection; ``main`` is the process ``hil run`` spawns (``python -m hil.tcu_node``) and
``hil tcu`` runs.  This module imports neither the command line nor the recorder.

Only frames that pass ``FrameCodec.classify`` and the step sequence check reach the identifier.
The samples travel as frames, so the plant side computes the run's fit metrics whichever TCU
answered; the node's own counters (rejected frames and readings, resyncs) go to ``--report FILE``
(JSON, written at exit) and, with ``--json``, to stdout.
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import can

from identifier import DEFAULT_STRATEGY, STRATEGIES, TractionIdentifier

from .errors import (EXIT_INTERRUPTED, EXIT_OK, BusError, ConfigError, HilError, PeerSilent, PlantFault,
                     caused_by_interrupt, remember_unraisable_interrupts)
from .bus.frames import (PLANT_IDS, STATE_FAULT, STATE_FINISHED, STATE_NAMES, STATE_RUNNING, STATE_STARTING,
                     FrameCodec, RejectCounter, SampleReport)
from .bus.mapping import codec_for
from .bus.link import GuardedBus, Sender, heartbeat_period_s, poll_until, silence_limit_s
from .bus.secoc import node_key
from .bus.verdicts import BAD_SEQUENCE, FRESH, RESENT, newest, sensor_sequence
from .period_account import ACCOUNT_ENV

#: a sensor step may jump ahead by at most this many periods (frames lost); beyond it is garbage
MAX_STEP_GAP = 100


class TcuNode:
    """Frames in, frames out: PlantSensor -> identifier -> TorqueCommand, TcuResult*, TcuStatus.

    ``realtime``: the node answers against deadlines, so its identifier runs the drill that keeps the
    strategy's code warm before a slip (``[identifier] drill_particles``); otherwise (lockstep, replay)
    nothing waits on a cold first sample and the drill would only cost time: it is off.  The drill
    changes no result (``identifier/drill.py``), so both give the same frames."""

    def __init__(self, scenario, strategy: str, seed: int, codec: FrameCodec | None = None, realtime: bool = False):
        settings = scenario.identifier_settings()
        if not realtime:     # the drill keeps code warm for deadlines (identifier/drill.py): none to keep here
            settings = dataclasses.replace(settings, drill_particles=0)
        self.settings = settings
        self.codec = codec or codec_for(scenario, auth=node_key(scenario.bus))
        self.scenario_digest = scenario.digest       # announced on the bus (TcuScenario) until the first reading
        #: a TCU's own DBC (hil/bus/mapping.py): readings count from the plant's 'running' heartbeat on
        self.mapped = getattr(self.codec, "mapped", False)
        self.probes = 0              # mapped: the plant's start-up probes, not answered
        law = scenario.control.law
        self.identifier = TractionIdentifier(self.settings, strategy, seed, law, scenario.control.options.get(law))
        self.last_demand_step = -1
        self._samples_base = 0       # samples sent before the identifier's last re-arm (indices run on)
        self._strategy = self.identifier.strategy
        self.rejected = RejectCounter()
        self.last_step = -1
        self._jump: int | None = None     # step of the last out-of-sequence sensor frame
        self.resyncs = 0
        self.sensor_frames = 0
        self.events = 0
        self.samples_sent = 0
        self.estimates_sent = 0      # entries of the identifier's estimate trace sent as TcuEstimate frames
        self.stale_skipped = 0       # sensor frames passed over after a stall (newest_sensor_only)
        self.resent = 0              # the last answered step's reading again: its command sent again
        self._last_command = None    # the TorqueCommand of the last answered step
        self.plant_state: int | None = None
        self.finished = False

    def handle(self, msg: can.Message, classified=None, send=None) -> list[can.Message]:
        """The replies to ``msg``; ``classified``: its ``codec.classify`` result when already taken (a
        frame is classified once: with authentication a second look would see a replay).  ``send``:
        called with the TorqueCommand frame as soon as it is known, before the identifier's drill and
        strategy run (the plant waits for the command, nothing waits for the rest); the list returned
        then holds the other replies.  Without it the command is the list's first frame."""
        frame, reason = classified or self.codec.classify(msg)
        if frame is None:
            self.rejected[reason] += 1
            return []
        if self.mapped and frame.name in ("PlantSensor", "DriverDemand", "MappedPart") \
                and self.plant_state != STATE_RUNNING:
            self.probes += frame.name == "PlantSensor"      # the plant's start-up probes: not the run yet
            return []
        if frame.name == "PlantSensor":
            reading = frame.value
            if frame.demand is not None:
                self.identifier.demand_nm = frame.demand.torque_nm
            verdict = sensor_sequence(reading.step, self.last_step, MAX_STEP_GAP)    # a run starts at step 0
            if verdict == RESENT:       # the plant's lockstep resend: its command was lost; the same again
                self.resent += 1
                return [self.codec.command(self._last_command)] if self._last_command is not None else []
            if verdict != FRESH:
                # out of sequence: garbage, unless the next frame continues it (the TCU lost many frames);
                # never back to a step already answered (a plant does not go back: those are old frames sent again)
                resync = self._jump is not None and reading.step == self._jump + 1 and reading.step > self.last_step
                self._jump = reading.step
                if not resync:
                    self.rejected[BAD_SEQUENCE] += 1
                    return []
                self.resyncs += 1
            self._jump = None
            self.last_step = reading.step
            self.sensor_frames += 1
            c = self.codec
            command = self.identifier.command(reading)
            self._last_command = command
            command_frame = c.command(command)
            if send is not None:     # the command out before the drill and the strategy run
                send(command_frame)
            out = self.identifier.work(command)
            self.events += len(out.events)
            # the command first: the plant waits for it; samples, results and status follow
            results = []
            for e in out.events:
                results.append(c.result(e))
                interval = c.interval(e)
                if interval is not None:
                    results.append(interval)
            return ([] if send is not None else [command_frame]) + self._new_samples(reading.step) + results \
                + self._new_estimates() + [c.status(out.status, out.observer)]
        if frame.name == "DriverDemand":
            if frame.value.step <= self.last_demand_step:
                self.rejected[BAD_SEQUENCE] += 1
                return []
            self.last_demand_step = frame.value.step
            self.identifier.demand_nm = frame.value.torque_nm
            return []
        if frame.name == "PlantHeartbeat":
            if self.mapped and frame.value.state == STATE_RUNNING and self.plant_state != STATE_RUNNING:
                self.codec.restart()       # the run's first reading is the next trigger frame
            self.plant_state = frame.value.state
            if frame.value.state in (STATE_FINISHED, STATE_FAULT):
                self.finished = True
        return []          # TCU frames of another node: nothing to do

    def _new_estimates(self) -> list[can.Message]:
        """A TcuEstimate frame for each estimate the identifier kept since the last call (its trace holds one in
        ``ESTIMATE_TRACE_STEPS`` periods, in closed loop); none for an estimate the frame cannot carry."""
        trace = self.identifier.estimate_trace
        if len(trace) == self.estimates_sent:
            return []
        new = trace[self.estimates_sent:]
        self.estimates_sent = len(trace)
        return [m for m in (self.codec.estimate(e) for e in new) if m is not None]

    def _new_samples(self, step: int) -> list[can.Message]:
        strategy = self.identifier.strategy
        if strategy is not self._strategy:          # re-armed: a fresh strategy, the indices run on
            self._strategy = strategy
            self._samples_base = self.samples_sent
        n = strategy.samples
        base = self._samples_base
        if base + n == self.samples_sent:
            return []
        v, mu = strategy.data()
        detected = self.identifier.detector.detected_step
        frames = [self.codec.sample(SampleReport(step, base + i, -1 if detected is None else detected, float(v[i]),
                                                 float(mu[i]))) for i in range(self.samples_sent - base, n)]
        self.samples_sent = base + n
        return frames

    def report(self) -> dict:
        ident = self.identifier
        return {"detected_step": ident.detector.detected_step, "events": self.events, "samples": self.samples_sent,
                "stale_skipped": self.stale_skipped, "resent": self.resent,
                "sensor_frames": self.sensor_frames, "probes": self.probes, "last_step": self.last_step, "resyncs": self.resyncs,
                "rejected_frames": dict(self.rejected), "rejected_readings": ident.rejected_readings,
                "plant_state": None if self.plant_state is None else STATE_NAMES.get(self.plant_state),
                "confirmed": bool(ident.strategy.confirmed), "rearms": ident.rearms}


def newest_sensor_only(bus: can.BusABC, first: can.Message, node: TcuNode, limit: int = 1000) -> list[tuple]:
    """``first`` and whatever else is already queued, each with its ``classify`` result (for
    ``TcuNode.handle``: a frame is classified once), with the stale sensor readings left out
    (counted in ``node.stale_skipped``): after a stall the TCU answers the plant's latest reading
    instead of working through a backlog it can never catch up with (real time only: in lockstep
    the plant sends one reading at a time, so a second one in the queue is not the plant's).

    A reading is stale when it decodes, is in sequence (after the last step answered, within
    ``MAX_STEP_GAP``) and a later frame of the batch carries a newer in-sequence step; anything else
    (garbage, out-of-sequence or forged steps) stays in the batch for ``TcuNode.handle`` to judge
    and count."""
    batch = [first]
    while len(batch) < limit and (msg := bus.recv(timeout=0.0)) is not None:
        batch.append(msg)
    classified = [node.codec.classify(m) for m in batch]
    steps = {i: frame.value.step for i, (m, (frame, _)) in enumerate(zip(batch, classified))
             if frame is not None and frame.name == "PlantSensor"
             and sensor_sequence(frame.value.step, node.last_step, MAX_STEP_GAP) == FRESH}
    stale = newest(steps)
    node.stale_skipped += len(stale)
    return [(m, c) for i, (m, c) in enumerate(zip(batch, classified)) if i not in stale]


def serve(bus: can.BusABC, node: TcuNode, *, silence_s: float, heartbeat_period_s: float,
          startup_timeout_s: float, realtime: bool = False, spin_s: float = 0.0, log=None,
          stop_requested=lambda: False) -> None:
    """Answer frames until the plant says it finished; raises PeerSilent when the plant goes quiet
    for longer than ``silence_s`` (or never shows up within ``startup_timeout_s``), and
    KeyboardInterrupt at the next frame or wait once ``stop_requested()`` (a SIGTERM whose interrupt
    could not be raised where it landed, e.g. inside a ctypes callback).  ``spin_s``
    (lockstep): poll the bus this long after each frame before sleeping in it, so the next sensor
    frame finds the node awake (``[bus] lockstep_spin_s``).

    Heartbeats, every ``heartbeat_period_s``: this loop sends them between frames, after its answers; in
    real time one due within the next exchange period goes out right after the answer to a reading, so it
    never reaches the plant just before the plant's next period starts.
    A thread is the backstop for work that holds the loop longer (a strategy's fit): it wakes
    ``max(heartbeat_period_s, silence_s / 4)`` after the last heartbeat and sends one when none went
    out for a period, so the plant never takes a busy TCU for a silent one.  Why not the thread
    alone: a thread that needs the interpreter every 2 ms takes it from the loop in the middle of an
    answer (at the send of the command, where the loop lets it go), and the command waits for the
    heartbeat's encoding, its MAC and its send."""
    sender = Sender(bus)
    codec = node.codec
    state = [STATE_STARTING]
    stop = threading.Event()
    sending = threading.Lock()          # one heartbeat at a time: each takes the next freshness value
    sent = {"counter": 0, "at": -math.inf}

    announce = getattr(codec, "tcu_scenario", None)      # a TCU's own DBC has no TcuScenario frame

    def send_heartbeat() -> None:
        with sending:
            if announce is not None and node.last_step < 0:     # until the first reading: the scenario it runs
                sender.send(announce(node.scenario_digest))
            sender.send(codec.tcu_heartbeat(sent["counter"], state[0], node.last_step))
            sent["counter"] += 1
            sent["at"] = time.monotonic()

    def backstop():      # wakes a backstop interval after the last heartbeat, whoever sent it
        while not stop.wait(max(sent["at"] + backstop_s - time.monotonic(), heartbeat_period_s)):
            if time.monotonic() - sent["at"] >= heartbeat_period_s:
                try:
                    send_heartbeat()
                except Exception:  # noqa: BLE001 - a dead bus shows up in the main loop
                    pass

    backstop_s = max(heartbeat_period_s, silence_s / 4)
    thread = threading.Thread(target=backstop, name="tcu-heartbeat", daemon=True)
    old_interval = sys.getswitchinterval()
    sys.setswitchinterval(min(old_interval, backstop_s / 4))   # heartbeats keep coming while fitting
    thread.start()
    t0 = time.monotonic()
    last_plant = None
    early_s = node.settings.period_s if realtime else 0.0
    answered_n = 0                     # real time: the readings answered when the last heartbeat check ran
    try:
        spinning = spin_s > 0.0 and not realtime
        while not node.finished:
            if stop_requested():
                raise KeyboardInterrupt
            msg = poll_until(bus, time.perf_counter() + spin_s) if spinning else None
            if msg is None:
                due = sent["at"] + heartbeat_period_s - time.monotonic()
                if due <= 0.0:
                    send_heartbeat()
                    due = heartbeat_period_s
                msg = bus.recv(timeout=min(0.05, silence_s / 4, due))
            now = time.monotonic()
            if msg is None:
                if last_plant is None:
                    if now - t0 > startup_timeout_s:
                        raise PeerSilent(f"no frame from the plant within {startup_timeout_s:g} s")
                elif now - last_plant > silence_s:
                    raise PeerSilent(f"plant silent for {(now - last_plant) * 1e3:.0f} ms (limit "
                                     f"{silence_s * 1e3:.0f} ms) after step {node.last_step}")
                continue
            for msg, classified in (newest_sensor_only(bus, msg, node) if realtime else ((msg, None),)):
                if msg.arbitration_id in PLANT_IDS and not msg.is_extended_id:
                    before = sum(node.rejected.values())
                    replies = node.handle(msg, classified, sender.send)
                    if sum(node.rejected.values()) == before:     # a valid plant frame: the plant lives
                        last_plant = now
                        state[0] = STATE_RUNNING
                else:
                    replies = node.handle(msg, classified)
                for r in replies:
                    sender.send(r)
            if early_s and node.sensor_frames != answered_n:
                # real time: a heartbeat due within the next period goes out now, right after the answer,
                # not at whatever moment it falls due (it may then reach the plant just before its next
                # period starts, and the plant's handling of it start that period late)
                answered_n = node.sensor_frames
                if sent["at"] + heartbeat_period_s - time.monotonic() <= early_s:
                    send_heartbeat()
        state[0] = STATE_FINISHED
    except BaseException:
        state[0] = STATE_FAULT
        raise
    finally:
        stop.set()
        thread.join(1.0)
        sys.setswitchinterval(old_interval)
        try:   # one last heartbeat that says how the TCU ended
            send_heartbeat()
        except Exception:  # noqa: BLE001
            pass


def build_parser(prog="python -m hil.tcu_node") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="The identifier (TCU) alone on a bus.")
    add_arguments(p)
    return p


def add_arguments(p) -> None:
    p.add_argument("scenario", nargs="?", default=None,
                   help="scenario TOML (the TCU uses its vehicle model, NFCC-0 and [identifier])")
    p.add_argument("--handover", metavar="FILE", default=None,
                   help="instead of SCENARIO: a scenario hand-over (JSON) as hil run writes it for its TCU process: "
                   "the resolved scenario, overrides included, and its digest")
    p.add_argument("--bus", default="auto", help="bus to listen on: auto | socketcan:<ch> | remote:<url> | "
                   "<python-can interface>:<channel> (default auto)")
    p.add_argument("--strategy", default=DEFAULT_STRATEGY, help=f"identification strategy (default {DEFAULT_STRATEGY})")
    p.add_argument("--seed", type=int, default=None, help="identifier seed (default: the scenario's)")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                   help="sets the plant-silence limit and heartbeat period (realtime: [bus] silence_periods x "
                   "heartbeat_period_s, default 25 x 2 ms; lockstep: [bus] lockstep_silence_s, default 1 s)")
    p.add_argument("--control", default=None, metavar="LAW", help="the control law (default: the scenario's "
                   "[control] law, else demand)")
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE", help="override a scenario field")
    p.add_argument("--wait", type=float, default=None, help="seconds to wait for the plant's first frame "
                   "(default: [bus] startup_timeout_s)")
    p.add_argument("--json", action="store_true", help="print the TCU's report as one JSON object on stdout")
    p.add_argument("--report", metavar="FILE", default=None, help="write the TCU's report (JSON) to FILE at exit")


def set_cpu_affinity(cpus, who: str, log) -> bool:
    """Pin this process to the CPU numbers ``cpus`` (nothing when empty); a refusal (EPERM, EINVAL, no
    ``sched_setaffinity``) is reported once through ``log`` and is not fatal. True when applied."""
    if not cpus:
        return False
    try:
        os.sched_setaffinity(0, set(cpus))
        return True
    except (AttributeError, OSError) as e:
        log(f"warning: cannot pin the {who} process to CPUs {list(cpus)} ({e}); running unpinned")
        return False


def run_tcu(args) -> int:
    """Shared by ``hil tcu`` and the child process; raises ``HilError`` for bad input."""
    from .bus.link import open_bus, resolve
    from .config import parse_set

    if args.strategy not in STRATEGIES:
        raise ConfigError(f"unknown strategy {args.strategy!r}; available: {', '.join(sorted(STRATEGIES))}")
    overrides = parse_set(args.set)
    if getattr(args, "control", None) is not None:
        overrides["control.law"] = args.control        # checked by the loader: an unknown law is one line
    scenario = _scenario(args, overrides)
    settings = scenario.bus
    seed = scenario.run.seed if args.seed is None else args.seed
    bus = resolve(args.bus)
    if bus in ("inprocess", "hub", "udp_multicast"):
        raise BusError(f"bus {args.bus}{' (no vcan0 here: hub)' if args.bus == 'auto' else ''}: the TCU alone needs "
                       "the plant's bus (socketcan:<ch>, remote:ws://HOST:PORT/ of a running hub, "
                       "udp_multicast:GROUP:PORT, or a python-can interface:channel)")
    from .progress import compile_kernels

    compile_kernels("hil tcu")      # before the bus: a first compile is shown, not spent inside the start-up wait
    node = TcuNode(scenario, args.strategy, seed, realtime=args.mode == "realtime")
    period = scenario.run.exchange_period_s
    code = EXIT_OK
    error = None
    account = None
    handle = open_bus(bus)
    _bus_open.append(True)
    try:        # from here the bus is closed whatever ends the process (a SIGTERM from the plant included)
        set_cpu_affinity(settings.cpu_affinity_tcu, "TCU", lambda m: print(m, file=sys.stderr, flush=True))
        if args.mode == "realtime":     # a full collection over scipy's and casadi's objects stalls both threads
            gc.freeze()
            gc.disable()
        guarded = GuardedBus(handle.bus, handle.name)
        account_path = os.environ.get(ACCOUNT_ENV)
        if account_path:        # hil bench period asked for the account of this process's periods
            from .period_account import install_tcu
            account = install_tcu(node, guarded, scenario.steps + 100)
        serve(guarded, node, silence_s=silence_limit_s(settings, args.mode, period),
              heartbeat_period_s=heartbeat_period_s(settings, args.mode),
              startup_timeout_s=settings.startup_timeout_s if args.wait is None else args.wait,
              realtime=args.mode == "realtime", spin_s=settings.lockstep_spin_s,
              stop_requested=lambda: bool(_terminated))
        if node.plant_state == STATE_FAULT:
            error = PlantFault(f"the plant reported a fault after step {node.last_step}")
    except PeerSilent as e:
        error = e
    finally:
        # the plant stops this process with SIGTERM once its run is over: the bus is closed and the
        # report written whole, not cut by the signal
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, signal.SIG_IGN)
        handle.close()
        if account is not None:
            account.close()
            account.save(account_path)
        report = node.report()
        report["exit"] = error.exit_code if error is not None else code
        report["error"] = None if error is None else str(error)
        _write_report(report, args.report, args.json)
    if error is not None:
        raise error
    return code


def _scenario(args, overrides: dict):
    """The scenario this TCU runs: SCENARIO with ``overrides``, or a hand-over (``--handover``) with this
    run's plumbing items (``hil.config.SESSION_BUS_KEYS``) over it; ``ConfigError`` for neither or both."""
    from .config import SESSION_BUS_KEYS, load_scenario, scenario_from_handover

    if (args.scenario is None) == (getattr(args, "handover", None) is None):
        raise ConfigError("give a scenario file or --handover FILE (one of them)")
    if args.handover is None:
        return load_scenario(args.scenario, overrides)
    try:
        data = json.loads(Path(args.handover).read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"--handover {args.handover}: cannot read: {e}") from None
    scenario = scenario_from_handover(data, f"--handover {args.handover}")
    foreign = sorted(k for k in overrides if not (k.startswith("bus.") and k[4:] in SESSION_BUS_KEYS))
    if foreign:
        raise ConfigError(f"--handover with --set {', '.join(foreign)}: a hand-over is the whole scenario; only "
                          f"bus.{', bus.'.join(SESSION_BUS_KEYS)} may be set beside it")
    if overrides:
        from .config import parse_scenario
        scenario = parse_scenario(scenario.source_text, scenario.path, {**scenario.overrides, **overrides})
    return scenario


def _clean(x):
    """JSON-safe: NaN and inf become None."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def _write_report(report: dict, path, to_stdout: bool) -> None:
    text = json.dumps(_clean(report))
    if path:
        tmp = f"{path}.tmp"
        try:
            with open(tmp, "w") as f:
                f.write(text)
            os.replace(tmp, path)     # the reader sees a whole report or none
        except OSError as e:          # the plant's report directory gone, or a full disk: say so, go on
            print(f"hil tcu: warning: report not written to {path}: {e.strerror or e}", file=sys.stderr, flush=True)
    if to_stdout:
        print(text, flush=True)


_terminated = []
_bus_open = []        # not empty once run_tcu holds the bus: from then on a SIGTERM unwinds to its cleanup


def _terminate(signum, frame):
    """SIGTERM (the plant ends its TCU this way).  Before the bus is open there is nothing to give back,
    and an interrupt raised inside an import is unsafe: a library may swallow it (the TCU then waits out
    its start-up timeout) or the interpreter may still die of SIGINT at exit, after the one line was
    printed (exit -2 instead of 130).  So until then the process ends here, with the one line.
    From the bus on, a ``KeyboardInterrupt`` unwinds ``run_tcu``, which closes the bus and writes the report."""
    _terminated.append(signum)
    if not _bus_open:
        os.write(2, b"hil tcu: interrupted\n")
        os._exit(EXIT_INTERRUPTED)
    raise KeyboardInterrupt


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    signal.signal(signal.SIGTERM, _terminate)
    # a SIGTERM landing inside a ctypes callback (numba compiling) cannot unwind there: _terminate
    # recorded it, the hook keeps the traceback off the run's stderr, and serve stops at its next turn
    remember_unraisable_interrupts(lambda: None)
    try:
        return run_tcu(args)
    except HilError as e:
        print(f"hil tcu: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("hil tcu: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:
        # the plant ends this process with SIGTERM; an extension module running then may turn the
        # interrupt into another error: still an interrupt, not a traceback on the run's stderr
        if not (_terminated or caused_by_interrupt(e)):
            raise
        print(f"hil tcu: interrupted ({type(e).__name__} on the way out: {e})", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)   # a SIGTERM while exiting just ends the process


if __name__ == "__main__":
    sys.exit(main())
