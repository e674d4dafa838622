"""The TCU on a bus: ``TcuNode`` turns received frames into reply frames around a ``TractionIdentifier``;
``serve`` runs a node on an open bus with heartbeats and plant-silence detection; ``main`` is the
process ``hil run`` spawns (``python -m hil.tcu_process``) and ``hil tcu`` runs.

Only frames that pass ``FrameCodec.classify`` and the step sequence check reach the identifier.
At the end the process prints one JSON report on stdout (``--report-json``): the identifier's
samples (for the fit metrics of the run summary), its detection step, the events it produced and
the rejected frames by reason.
"""
from __future__ import annotations

import argparse
import gc
import json
import signal
import sys
import threading
import time

import can

from identifier import TractionIdentifier

from .frames import (PLANT_IDS, STATE_FAULT, STATE_FINISHED, STATE_NAMES,
                     STATE_RUNNING, STATE_STARTING, FrameCodec, RejectCounter)
from .summary import clean

#: a sensor step may jump ahead by at most this many periods (frames lost); beyond it is garbage
MAX_STEP_GAP = 100

EXIT_OK, EXIT_USAGE, EXIT_SILENT, EXIT_PLANT_FAULT, EXIT_INTERRUPTED = 0, 2, 3, 4, 130


class PeerSilent(RuntimeError):
    """The other side of the bus stopped sending; the message is one line."""


class TcuNode:
    """Frames in, frames out: PlantSensor -> identifier -> TorqueCommand, TcuResult*, TcuStatus."""

    def __init__(self, scenario, strategy: str, seed: int, codec: FrameCodec | None = None):
        self.settings = scenario.identifier_settings()
        self.codec = codec or FrameCodec(scenario.run.exchange_period_s)
        self.identifier = TractionIdentifier(self.settings, strategy, seed)
        self.rejected = RejectCounter()
        self.last_step = -1
        self._jump: int | None = None     # step of the last out-of-sequence sensor frame
        self.resyncs = 0
        self.sensor_frames = 0
        self.events = 0
        self.plant_state: int | None = None
        self.finished = False

    def handle(self, msg: can.Message) -> list[can.Message]:
        frame, reason = self.codec.classify(msg)
        if frame is None:
            self.rejected[reason] += 1
            return []
        if frame.name == "PlantSensor":
            reading = frame.value
            if not (self.last_step < reading.step <= self.last_step + MAX_STEP_GAP):    # a run starts at step 0
                # out of sequence: garbage, unless the next frame continues it (the TCU lost many frames)
                resync = self._jump is not None and reading.step == self._jump + 1
                self._jump = reading.step
                if not resync:
                    self.rejected["bad_sequence"] += 1
                    return []
                self.resyncs += 1
            self._jump = None
            self.last_step = reading.step
            self.sensor_frames += 1
            out = self.identifier.on_sensor(reading)
            self.events += len(out.events)
            c = self.codec
            # the command first: the plant waits for it; results and status follow
            return [c.command(out.command)] + [c.result(e) for e in out.events] + [c.status(out.status, out.observer)]
        if frame.name == "PlantHeartbeat":
            self.plant_state = frame.value.state
            if frame.value.state in (STATE_FINISHED, STATE_FAULT):
                self.finished = True
        return []          # TCU frames of another node: nothing to do

    def report(self) -> dict:
        v, mu = self.identifier.strategy.data()
        ident = self.identifier
        return {"samples_v": [float(x) for x in v], "samples_mu": [float(x) for x in mu],
                "detected_step": ident.detector.detected_step, "events": self.events,
                "sensor_frames": self.sensor_frames, "last_step": self.last_step, "resyncs": self.resyncs,
                "rejected_frames": dict(self.rejected), "rejected_readings": ident.rejected_readings,
                "plant_state": None if self.plant_state is None else STATE_NAMES.get(self.plant_state),
                "confirmed": bool(ident.strategy.confirmed)}


class Sender:
    """Thread-safe ``send`` (the heartbeat thread and the main loop share the bus)."""

    def __init__(self, bus: can.BusABC):
        self.bus = bus
        self._lock = threading.Lock()
        self.sent = 0

    def send(self, msg: can.Message) -> None:
        with self._lock:
            for attempt in range(50):
                try:
                    self.bus.send(msg, timeout=0.1)
                    self.sent += 1
                    return
                except can.CanOperationError:
                    if attempt == 49:
                        raise
                    time.sleep(0.0005)   # transmit queue full (ENOBUFS): wait a little


def serve(bus: can.BusABC, node: TcuNode, *, silence_s: float, heartbeat_period_s: float,
          startup_timeout_s: float, log=None) -> None:
    """Answer frames until the plant says it finished; raises PeerSilent when the plant goes quiet
    for longer than ``silence_s`` (or never shows up within ``startup_timeout_s``)."""
    sender = Sender(bus)
    codec = node.codec
    state = [STATE_STARTING]
    stop = threading.Event()

    def heartbeat():
        counter = 0
        next_t = time.monotonic()
        while not stop.is_set():
            try:
                sender.send(codec.tcu_heartbeat(counter, state[0], node.last_step))
            except Exception:  # noqa: BLE001 - a dead bus shows up in the main loop
                pass
            counter += 1
            next_t += heartbeat_period_s
            stop.wait(max(0.0, next_t - time.monotonic()))

    thread = threading.Thread(target=heartbeat, name="tcu-heartbeat", daemon=True)
    old_interval = sys.getswitchinterval()
    sys.setswitchinterval(min(old_interval, heartbeat_period_s / 4))   # heartbeats keep coming while fitting
    thread.start()
    t0 = time.monotonic()
    last_plant = None
    try:
        while not node.finished:
            msg = bus.recv(timeout=min(0.05, silence_s / 4))
            now = time.monotonic()
            if msg is None:
                if last_plant is None:
                    if now - t0 > startup_timeout_s:
                        raise PeerSilent(f"no frame from the plant within {startup_timeout_s:g} s")
                elif now - last_plant > silence_s:
                    raise PeerSilent(f"plant silent for {(now - last_plant) * 1e3:.0f} ms (limit "
                                     f"{silence_s * 1e3:.0f} ms) after step {node.last_step}")
                continue
            if msg.arbitration_id in PLANT_IDS and not msg.is_extended_id:
                before = sum(node.rejected.values())
                replies = node.handle(msg)
                if sum(node.rejected.values()) == before:     # a valid plant frame: the plant lives
                    last_plant = now
                    state[0] = STATE_RUNNING
            else:
                replies = node.handle(msg)
            for r in replies:
                sender.send(r)
        state[0] = STATE_FINISHED
    except BaseException:
        state[0] = STATE_FAULT
        raise
    finally:
        stop.set()
        thread.join(1.0)
        sys.setswitchinterval(old_interval)
        try:   # one last heartbeat that says how the TCU ended
            sender.send(codec.tcu_heartbeat(0, state[0], node.last_step))
        except Exception:  # noqa: BLE001
            pass


def silence_limit_s(settings, mode: str, period_s: float) -> float:
    """How long the peer may send nothing before it counts as silent (wall seconds).

    Realtime: ``silence_periods`` periods of the heartbeat, the one frame a node sends however busy
    it is (``max(heartbeat_period_s, period_s)``; defaults 3 x 2 ms).  Lockstep: ``lockstep_silence_s``
    (a lockstep period has no wall-clock length, and a TCU busy fitting is not silent)."""
    if mode == "realtime":
        return settings.silence_periods * max(settings.heartbeat_period_s, period_s)
    return settings.lockstep_silence_s


def heartbeat_period_s(settings, mode: str) -> float:
    """Realtime: ``[bus] heartbeat_period_s``.  Lockstep: a quarter of the silence limit (the peers wait
    for each other by design; frequent heartbeats would only cost syscalls, which are dear in UML)."""
    return settings.heartbeat_period_s if mode == "realtime" else settings.lockstep_silence_s / 4


def build_parser(prog="python -m hil.tcu_process") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="The identifier (TCU) alone on a bus.")
    add_arguments(p)
    return p


def add_arguments(p) -> None:
    p.add_argument("scenario", help="scenario TOML (the TCU uses its vehicle model, NFCC-0 and [identifier])")
    p.add_argument("--bus", default="auto", help="bus to listen on: auto | socketcan:<ch> | remote:<url> | "
                   "<python-can interface>:<channel> (default auto)")
    p.add_argument("--strategy", default="nlls", help="identification strategy")
    p.add_argument("--seed", type=int, default=None, help="identifier seed (default: the scenario's)")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                   help="sets the plant-silence limit and heartbeat period (realtime: [bus] silence_periods x "
                   "heartbeat_period_s, default 3 x 2 ms; lockstep: [bus] lockstep_silence_s, default 1 s)")
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE", help="override a scenario field")
    p.add_argument("--wait", type=float, default=None, help="seconds to wait for the plant's first frame "
                   "(default: [bus] startup_timeout_s)")
    p.add_argument("--json", action="store_true", help="print the TCU's report as one JSON object on stdout")


def run_tcu(args) -> int:
    """Shared by ``hil tcu`` and the child process; raises UserError-like exceptions for bad input."""
    from identifier import STRATEGIES

    from .bus import BusError, open_bus
    from .canloop import bus_settings
    from .commands.run import parse_set
    from .scenario import load_scenario

    if args.strategy not in STRATEGIES:
        raise BusError(f"unknown strategy {args.strategy!r}; available: {', '.join(sorted(STRATEGIES))}")
    scenario = load_scenario(args.scenario, parse_set(args.set))
    settings = bus_settings(scenario)
    seed = scenario.run.seed if args.seed is None else args.seed
    from .bus import resolve

    bus = resolve(args.bus)
    if bus in ("inprocess", "hub"):
        raise BusError(f"bus {args.bus}{' (no vcan0 here: hub)' if args.bus == 'auto' else ''}: the TCU alone needs "
                       "the plant's bus (socketcan:<ch>, remote:ws://HOST:PORT/ of a running hub, or a python-can "
                       "interface:channel)")
    handle = open_bus(bus)
    node = TcuNode(scenario, args.strategy, seed)
    if args.mode == "realtime":     # a full collection over scipy's and casadi's objects stalls both threads
        gc.freeze()
        gc.disable()
    period = scenario.run.exchange_period_s
    code = EXIT_OK
    try:
        serve(handle.bus, node, silence_s=silence_limit_s(settings, args.mode, period),
              heartbeat_period_s=heartbeat_period_s(settings, args.mode),
              startup_timeout_s=settings.startup_timeout_s if args.wait is None else args.wait)
        if node.plant_state == STATE_FAULT:
            print(f"hil tcu: the plant reported a fault after step {node.last_step}", file=sys.stderr)
            code = EXIT_PLANT_FAULT
    except PeerSilent as e:
        print(f"hil tcu: error: {e}", file=sys.stderr)
        code = EXIT_SILENT
    finally:
        handle.close()
        if args.json:
            report = node.report()
            report["exit"] = code
            print(json.dumps(clean(report)), flush=True)
    return code


def _terminate(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    from .bus import BusError
    from .scenario import ScenarioError

    args = build_parser().parse_args(argv)
    signal.signal(signal.SIGTERM, _terminate)
    try:
        return run_tcu(args)
    except (BusError, ScenarioError) as e:
        print(f"hil tcu: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("hil tcu: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)   # a SIGTERM while exiting just ends the process


if __name__ == "__main__":
    sys.exit(main())
