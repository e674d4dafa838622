"""The plant side of a HIL run over a CAN bus, and ``run_can`` that wires plant, TCU process, bus and recording.

Per exchange period k the plant senses, sends ``PlantSensor(k)`` and waits for ``TorqueCommand(k)``:
- ``lockstep``: it waits as long as the TCU needs (deterministic; as fast as the bus allows);
- ``realtime``: period k starts at ``t0 + k * period`` of the wall clock; the command must arrive
  before ``deadline_fraction`` of the period, otherwise the deadline is missed and the previous
  torque is held.  Period jitter, lateness, round trip and misses go to ``/loop/timing``.

Every frame sent and received is recorded raw on ``/can/frames`` (id, data, flags, the interface's
timestamp ``send_time_ns``, the host wall clock ``wall_time_ns``, the plant's sim time ``t_s``, direction and
the validation status).  Valid TCU frames are also recorded decoded on ``/tcu/command``,
``/tcu/status``, ``/tcu/observer`` and ``/tcu/identification``, so a log has the same topics whatever
the bus.

Heartbeats (PlantHeartbeat, TcuHeartbeat) flow both ways: in realtime every ``heartbeat_period_s``
(default 2 ms, from a thread in the TCU so it keeps beating while it fits), in lockstep every
``lockstep_silence_s / 4``.  Fault handling: the TCU silent (no valid frame of any kind) for more than
``silence_periods`` heartbeat periods (realtime; default 3 x 2 ms) or ``lockstep_silence_s`` (lockstep;
default 1 s) raises ``PeerSilent``; ``run_can`` records the fault (event + ``fault`` metadata), tells the
TCU, closes the MCAP and re-raises; ``hil run`` exits 3.  The TCU applies the same rule to the plant.
Malformed, unknown or out-of-range frames, and frames whose step is out of sequence, are counted by
reason, recorded with that reason as their status, and dropped.

Fit metrics (MSE ...) come from the TCU's own samples: the TCU process prints them in its JSON
report when the plant says it finished; in process the node hands them over directly.
"""
from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from identifier.messages import STAGE_NAMES, TorqueCommand

from .bus import BusError, die_with_parent, open_bus
from .frames import (DBC_PATH, STATE_FAULT, STATE_FINISHED, STATE_RUNNING, STATE_STARTING, TCU_IDS, FrameCodec,
                     RejectCounter, bus_load, format_bus_load)
from .loop import LAG_WINDOW_S, PlantSide, collector_paused, log_path, start_recording
from .progress import Progress
from .recording import interrupts_between_writes
from .scenario import ScenarioError
from .summary import clean, observer_lag_by_step, summarise
from .tcu_process import PeerSilent, Sender, TcuNode, heartbeat_period_s, silence_limit_s

LOAD_WARN_PERCENT = 70.0
CHILD_EXIT_TIMEOUT_S = 20.0
MODES = ("lockstep", "realtime")


@dataclass(frozen=True)
class BusSettings:
    """The scenario's optional ``[bus]`` table."""
    bitrate: int = 1_000_000              # arbitration bit rate, bit/s (for the bus-load figure)
    data_bitrate: int = 5_000_000         # CAN FD data-phase bit rate, bit/s
    heartbeat_period_s: float = 0.002     # wall-clock period of the heartbeats, both ways
    silence_periods: int = 3              # realtime: peer silent after this many heartbeat periods
    lockstep_silence_s: float = 1.0       # lockstep: peer silent after this many wall seconds
    startup_timeout_s: float = 60.0       # wait for the other side's first frame
    deadline_fraction: float = 0.9        # realtime: the command is due this far into the period
    rt_priority: int = 0                  # realtime: SCHED_FIFO priority for plant, hub and TCU (0: off)


def bus_settings(scenario) -> BusSettings:
    table = scenario.extra.get("bus", {}) or {}
    if not isinstance(table, dict):
        raise ScenarioError(f"{scenario.path}: [bus]: must be a table")
    fields = {f.name: f for f in dataclasses.fields(BusSettings)}
    values = {}
    for key, value in table.items():
        if key not in fields:
            raise ScenarioError(f"{scenario.path}: [bus] {key}: unknown key (known: {', '.join(fields)})")
        want = fields[key].type
        floor_ok = value >= 0 if key == "rt_priority" else value > 0
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not floor_ok:
            raise ScenarioError(f"{scenario.path}: [bus] {key}: must be a {'non-negative' if key == 'rt_priority' else 'positive'} "
                                f"number, got {value!r}")
        if want == "int" and not isinstance(value, int):
            raise ScenarioError(f"{scenario.path}: [bus] {key}: must be an integer, got {value!r}")
        values[key] = value
    s = BusSettings(**values)
    if s.deadline_fraction >= 1:
        raise ScenarioError(f"{scenario.path}: [bus] deadline_fraction: must be < 1, got {s.deadline_fraction!r}")
    return s


def _percentile(xs, q):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.percentile(xs, q)) if xs else None


class PlantNode:
    """The plant on a bus: sends sensor frames and heartbeats, receives everything, records it."""

    def __init__(self, scenario, seed: int, bus, recorder, mode: str, settings: BusSettings, *,
                 strategy: str, child: subprocess.Popen | None = None, watch_silence: bool = True, plant=None):
        self.scenario = scenario
        self.period_s = scenario.run.exchange_period_s
        from .reality_bus import Reality   # [reality] table / --reality: a "real" run, on the plant side only
        self.reality = Reality(scenario, seed)
        self.plant_side = PlantSide(scenario, seed, recorder, plant=plant if plant is not None else self.reality.plant)
        self.plant_side.sensors = self.reality.wrap_sensors(self.plant_side.sensors)
        self.codec = FrameCodec(self.period_s)
        self.bus = bus
        self.sender = Sender(bus)
        self.rec = recorder
        self.mode = mode
        self.settings = settings
        self.strategy = strategy
        self.child = child
        self.watch_silence = watch_silence
        self.silence_s = silence_limit_s(settings, mode, self.period_s)
        self.heartbeat_s = heartbeat_period_s(settings, mode)
        self.rejected = RejectCounter()
        self.commands: dict[int, TorqueCommand] = {}
        self.awaited = -1
        self.last_status_step = -1
        self.last_result_step = -1
        self.events = []
        self.observer_mu: dict[int, float] = {}
        self.tcu_state: int | None = None
        self.last_tcu_rx: float | None = None
        self.frames_tx = 0
        self.frames_rx = 0
        self.late_commands = 0
        self.hb_counter = 0
        self.next_hb = 0.0
        self.timing = {"period_us": [], "round_trip_us": [], "lateness_us": [], "missed": 0}

    # -- frames ------------------------------------------------------------------------------
    @property
    def t_s(self) -> float:
        return self.plant_side.plant.t_s

    def _record_frame(self, msg, direction: str, status: str, wall_ns: int) -> None:
        if self.rec is None:
            return
        self.rec.write("/can/frames", self.t_s, t_s=self.t_s, wall_time_ns=wall_ns,
                       send_time_ns=int(round((msg.timestamp or 0.0) * 1e9)), arbitration_id=msg.arbitration_id,
                       is_extended_id=bool(msg.is_extended_id), is_fd=bool(msg.is_fd),
                       is_error_frame=bool(msg.is_error_frame), is_remote_frame=bool(msg.is_remote_frame),
                       bitrate_switch=bool(msg.bitrate_switch), dlc=int(msg.dlc), data=bytes(msg.data),
                       direction=direction, status=status)

    def send(self, msg) -> None:
        msg.timestamp = time.time()
        self.sender.send(msg)
        self.frames_tx += 1
        self._record_frame(msg, "tx", "ok", time.time_ns())

    def heartbeat(self, state: int) -> None:
        self.send(self.codec.plant_heartbeat(self.hb_counter, state, max(self.awaited, 0)))
        self.hb_counter += 1

    def _heartbeat_if_due(self, now: float) -> None:
        if now >= self.next_hb:
            self.heartbeat(STATE_RUNNING)
            self.next_hb += self.heartbeat_s
            if self.next_hb <= now:           # fell behind (or the first one): restart the schedule
                self.next_hb = now + self.heartbeat_s

    def on_rx(self, msg) -> None:
        wall_ns = time.time_ns()
        self.frames_rx += 1
        frame, status = self.codec.classify(msg)
        if frame is not None:
            status = self._accept(frame)
        if status not in ("ok", "late"):
            self.rejected[status] += 1
        elif msg.arbitration_id in TCU_IDS:
            self.last_tcu_rx = time.monotonic()
        self._record_frame(msg, "rx", status, wall_ns)

    def _accept(self, frame) -> str:
        name, v, rec = frame.name, frame.value, self.rec
        current = self.awaited
        if name == "TorqueCommand":
            if v.step == self.awaited:
                self.commands[v.step] = v
            elif v.step < self.awaited:
                self.late_commands += 1
                return "late"
            else:
                return "bad_sequence"
            if rec:
                t = v.step * self.period_s
                rec.write("/tcu/command", t, step=v.step, t_s=t, torque_nm=v.torque_nm)
            return "ok"
        if name == "TcuStatus":
            st, obs = v
            if not (self.last_status_step < st.step <= current):
                return "bad_sequence"
            self.last_status_step = st.step
            t = st.step * self.period_s
            if obs is not None:
                if 0 <= obs.t_s - self.scenario.run.fault_time_s <= LAG_WINDOW_S + self.period_s:
                    self.observer_mu[obs.step] = obs.mu_hat
                if rec:
                    rec.write("/tcu/observer", obs.t_s, step=obs.step, t_s=obs.t_s,
                              creep_speed_kmh=obs.creep_speed_kmh, mu_hat=obs.mu_hat,
                              load_torque_nm=obs.load_torque_nm)
            if rec:
                rec.write("/tcu/status", t, step=st.step, t_s=t, stage=st.stage, stage_name=STAGE_NAMES[st.stage],
                          correction=st.correction)
            return "ok"
        if name == "TcuResult":
            e = v
            if not (self.last_result_step <= e.step <= current):
                return "bad_sequence"
            self.last_result_step = e.step
            self.events.append(e)
            if rec:
                rec.write("/tcu/identification", e.t_s, step=e.step, t_s=e.t_s, kind=e.kind, correction=e.correction,
                          params=list(e.params), j_ef=e.j_ef, samples=e.samples, strategy=self.strategy)
                rec.event(e.t_s, "INFO", f"{e.kind} Q={e.correction} after {e.samples} samples: "
                          + ", ".join(f"{x:.5g}" for x in e.params))
            return "ok"
        if name == "TcuHeartbeat":
            self.tcu_state = v.state
            return "ok"
        return "foreign"        # plant frames from another node on the bus

    # -- waiting -----------------------------------------------------------------------------
    def check_alive(self) -> None:
        if self.child is not None and self.child.poll() is not None:
            raise PeerSilent(f"TCU process exited with code {self.child.returncode} at step {self.awaited}")
        if self.tcu_state == STATE_FAULT:
            raise PeerSilent(f"TCU reported a fault at step {self.awaited}")
        if not self.watch_silence or self.last_tcu_rx is None:
            return
        quiet = time.monotonic() - self.last_tcu_rx
        if quiet > self.silence_s:
            raise PeerSilent(f"TCU silent for {quiet * 1e3:.1f} ms (limit {self.silence_s * 1e3:.1f} ms) at step "
                             f"{self.awaited}, t = {self.t_s:.4f} s")

    def _poll(self, until: float | None) -> None:
        """Receive one frame or wait at most until ``until`` (perf_counter) / the next heartbeat."""
        now = time.perf_counter()
        self._heartbeat_if_due(now)
        timeout = self.next_hb - now
        if until is not None:
            timeout = min(timeout, until - now)
        timeout = min(timeout, self.silence_s / 4)
        msg = self.bus.recv(timeout=max(timeout, 0.0))
        if msg is not None:
            self.on_rx(msg)
        self.check_alive()

    def await_command(self, k: int, deadline: float | None) -> TorqueCommand | None:
        while k not in self.commands:
            if deadline is not None and time.perf_counter() >= deadline:
                return None
            self._poll(deadline)
        return self.commands.pop(k)

    def idle_until(self, t: float, spin_s: float = 0.0) -> None:
        """Handle frames until ``t`` (perf_counter); the last ``spin_s`` is a busy wait for accuracy."""
        while time.perf_counter() < t - spin_s:
            self._poll(t - spin_s)
        while time.perf_counter() < t:
            pass

    def wait_for_tcu(self) -> None:
        """Heartbeats 'starting' until the TCU shows up."""
        t0 = time.monotonic()
        while self.last_tcu_rx is None:
            if time.monotonic() - t0 > self.settings.startup_timeout_s:
                raise PeerSilent(f"no TCU answered within {self.settings.startup_timeout_s:g} s")
            now = time.perf_counter()
            if now >= self.next_hb:
                self.heartbeat(STATE_STARTING)
                self.next_hb = now + min(self.heartbeat_s, 0.05)
            msg = self.bus.recv(timeout=min(self.heartbeat_s, 0.05))
            if msg is not None:
                self.on_rx(msg)
            self.check_alive()

    # -- the loop ----------------------------------------------------------------------------
    def step(self, k: int, deadline: float | None) -> None:
        ps = self.plant_side
        self.awaited = k
        reading = self.reality.deliver(ps.sense())
        t_send = time.perf_counter()
        self.send(self.codec.sensor(reading))
        cmd = self.await_command(k, deadline)
        now = time.perf_counter()
        if cmd is None:
            self.timing["missed"] += 1
            self.timing["round_trip_us"].append(math.nan)
            cmd = TorqueCommand(k, ps.plant.state.torque_nm)    # hold the torque being applied
            missed = True
        else:
            self.timing["round_trip_us"].append((now - t_send) * 1e6)
            missed = False
        ps.apply(cmd)
        return missed

    def run(self, steps: int, bar: Progress | None = None) -> None:
        period = self.period_s
        realtime = self.mode == "realtime"
        with collector_paused(realtime):
            t0 = time.perf_counter() + 0.005
            prev = None
            for k in range(steps):
                if realtime:
                    t_k = t0 + k * period
                    self.idle_until(t_k)
                    deadline = t_k + self.settings.deadline_fraction * period
                else:
                    t_k = deadline = None
                start = time.perf_counter()
                missed = self.step(k, deadline)
                lateness = (start - t_k) * 1e6 if realtime else 0.0
                period_us = math.nan if prev is None else (start - prev) * 1e6
                prev = start
                self.timing["period_us"].append(period_us)
                self.timing["lateness_us"].append(lateness)
                if self.rec:
                    self.rec.write("/loop/timing", k * period, step=k, t_s=k * period, period_us=period_us,
                                   round_trip_us=self.timing["round_trip_us"][-1], lateness_us=lateness,
                                   missed_deadline=missed)
                if bar is not None and k % 200 == 0:
                    bar.update(k)
            self.awaited = steps

    def finish(self, state: int = STATE_FINISHED) -> None:
        """Tell the TCU the run is over (it then reports and exits)."""
        for _ in range(2):
            try:
                self.heartbeat(state)
            except Exception:  # noqa: BLE001 - the bus may be gone on an abort
                return

    def drain(self) -> None:
        """Record what is still queued."""
        while True:
            msg = self.bus.recv(timeout=0.0)
            if msg is None:
                return
            self.on_rx(msg)

    def drain_until_child_exits(self, timeout_s: float) -> None:
        """Record the TCU's last frames while its process ends (an external TCU, no child: for
        ``timeout_s``, its last status and 'finished' heartbeat)."""
        end = time.monotonic() + timeout_s
        while (self.child is None or self.child.poll() is None) and time.monotonic() < end:
            msg = self.bus.recv(timeout=0.01)
            if msg is not None:
                self.on_rx(msg)
        self.drain()

    def timing_summary(self) -> dict:
        t = self.timing
        out = {"round_trip_p50_us": _percentile(t["round_trip_us"], 50),
               "round_trip_p99_us": _percentile(t["round_trip_us"], 99)}
        if self.mode == "realtime":
            nominal = self.period_s * 1e6
            jitter = [abs(p - nominal) for p in t["period_us"] if math.isfinite(p)]
            out.update({"missed_deadlines": t["missed"], "jitter_p99_us": _percentile(jitter, 99),
                        "jitter_max_us": max(jitter) if jitter else None,
                        "lateness_p99_us": _percentile(t["lateness_us"], 99), "late_commands": self.late_commands})
        return out


# -- wiring ------------------------------------------------------------------------------------------
def _child_command(scenario, strategy, seed, peer_spec, mode, set_args) -> list[str]:
    cmd = [sys.executable, "-m", "hil.tcu_process", str(scenario.path), "--bus", peer_spec, "--strategy", strategy,
           "--seed", str(seed), "--mode", mode, "--json"]
    for item in set_args or []:
        cmd += ["--set", item]
    return cmd


def _stop_child(child: subprocess.Popen | None) -> None:
    if child is None or child.poll() is not None:
        return
    child.terminate()
    try:
        child.wait(5)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()


def run_can(scenario, strategy: str = "nlls", seed: int | None = None, bus: str = "auto", mode: str = "lockstep",
            out_dir=None, record: bool = True, progress: bool | None = None, set_args=None, log=None,
            plant=None, external_tcu: bool = False) -> dict:
    """One HIL run over a bus: the TCU in its own process (in this thread for ``inprocess``).

    ``set_args``: the ``--set`` overrides that produced ``scenario`` (the TCU process loads the
    scenario again with them).  ``plant``: a plant object instead of the CasADi model (as
    ``run_inprocess``; see hil/plant_factory.py), closed by the caller.  Raises ``BusError`` for a
    bus that cannot be used, ``PeerSilent`` when the TCU falls silent (the MCAP then holds the
    fault and is closed), ``KeyboardInterrupt`` on Ctrl-C or SIGTERM (likewise).
    ``external_tcu``: start no TCU; one already on the bus (``hil tcu``, a real TCU) answers.  The
    summary then has the events from the result frames but no fit metrics (the samples stay in
    that TCU: ``hil tcu --json`` prints them).
    """
    if mode not in MODES:
        raise BusError(f"unknown mode {mode!r}; available: {', '.join(MODES)}")
    log = log or (lambda text: print(text, file=sys.stderr))
    seed = scenario.run.seed if seed is None else seed
    settings = bus_settings(scenario)
    period = scenario.run.exchange_period_s
    codec = FrameCodec(period)
    load = bus_load(codec.db, period, settings.heartbeat_period_s, settings.bitrate, settings.data_bitrate)

    plant_obj, plant = plant, None
    old_sched = _set_rt_priority(settings.rt_priority, log) if mode == "realtime" and settings.rt_priority > 0 \
        else None
    child = None
    handle = None
    rec = None
    summary = None
    path = None
    with interrupts_between_writes():   # SIGTERM ends a run like Ctrl-C, never mid-write
        try:
            if bus == "inprocess":
                tcu = TcuNode(scenario, strategy, seed)
                handle = open_bus("inprocess", inprocess_node=tcu)
            else:
                tcu = None
                handle = open_bus(bus)
                if external_tcu and handle.hub is not None:
                    raise BusError("bus hub: a hub started here has no external TCU on it; start one with "
                                   "python -m can_remote and give both sides --bus remote:ws://127.0.0.1:PORT/")
                if handle.peer_spec is None and not external_tcu:
                    raise BusError(f"bus {handle.name}: reachable only inside this process; a TCU process cannot "
                                   "join it (use inprocess, hub or socketcan:<ch>)")
            if tcu is None and not external_tcu:
                child = subprocess.Popen(_child_command(scenario, strategy, seed, handle.peer_spec, mode, set_args),
                                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True,
                                         start_new_session=True, preexec_fn=die_with_parent,
                                         env={**os.environ, "PYTHONUNBUFFERED": "1"})
            log(format_bus_load(load) + f" on {handle.name}")
            if load["load_percent"] > LOAD_WARN_PERCENT:
                log(f"warning: bus load {load['load_percent']:.1f} % is above {LOAD_WARN_PERCENT:g} % "
                    f"(raise [bus] bitrate/data_bitrate or the exchange period)")
            path = log_path(scenario, strategy, seed, out_dir) if record else None
            if record:
                rec = start_recording(scenario, strategy, seed, handle.name, mode, path)
                rec.metadata("dbc", {"name": DBC_PATH.name, "text": DBC_PATH.read_text()})
                rec.metadata("bus", {"spec": bus, "name": handle.name, "dbc": DBC_PATH.name,
                                     **{k: repr(v) for k, v in dataclasses.asdict(settings).items()},
                                     "load_percent": f"{load['load_percent']:.2f}"})
            if rec and hasattr(plant_obj, "metadata"):
                rec.metadata("plant", plant_obj.metadata())
            plant = PlantNode(scenario, seed, handle.bus, rec, mode, settings, strategy=strategy, child=child,
                              watch_silence=tcu is None, plant=plant_obj)
            if tcu is None:
                plant.wait_for_tcu()
            bar = Progress(scenario.steps, f"{scenario.name} {strategy} {handle.name} {mode}", progress)
            wall0 = time.perf_counter()
            try:
                plant.run(scenario.steps, bar)
            finally:
                bar.close()
            wall = time.perf_counter() - wall0
            plant.finish(STATE_FINISHED)
            if tcu is not None:
                plant.drain()
                report = tcu.report()
            elif external_tcu:
                plant.drain_until_child_exits(0.2)
                report = {"samples_v": [], "samples_mu": [], "detected_step": None, "external": True}
            else:
                plant.drain_until_child_exits(CHILD_EXIT_TIMEOUT_S)
                report = _child_report(child)
            summary = _summary(scenario, strategy, seed, handle.name, mode, plant, report, path, wall, load)
            if rec:
                summary["messages"] = rec.messages + 1   # + the summary itself
        except PeerSilent as e:
            if rec and plant is not None:
                rec.event(plant.t_s, "ERROR", f"fault: {e}")
                rec.metadata("fault", {"reason": str(e), "step": str(plant.awaited), "t_s": repr(plant.t_s)})
            if plant is not None:
                plant.finish(STATE_FAULT)
            raise
        except KeyboardInterrupt:
            if rec and plant is not None:
                rec.event(plant.t_s, "ERROR", "run interrupted (SIGINT/SIGTERM)")   # one write: already atomic
            if plant is not None:
                plant.finish(STATE_FAULT)
            raise
        finally:
            if rec:
                with rec.atomic():
                    if summary is None and plant is not None:
                        rec.event(plant.t_s, "ERROR", "run aborted")
                    if plant is not None:
                        plant.reality.record_truth(rec)
                    rec.close(summary)
            _stop_child(child)
            if child is not None and child.stdout:
                child.stdout.close()
            if handle is not None:
                handle.close()
            if old_sched is not None:
                os.sched_setscheduler(0, *old_sched)
    return summary


def _set_rt_priority(priority: int, log) -> None:
    """SCHED_FIFO for this process; the hub and TCU processes started after it inherit it."""
    try:
        old = (os.sched_getscheduler(0), os.sched_getparam(0))
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        log(f"realtime: SCHED_FIFO priority {priority}")
        return old
    except (AttributeError, PermissionError, OSError) as e:
        log(f"warning: cannot set SCHED_FIFO priority {priority} ({e}); running at normal priority")
        return None


def _child_report(child) -> dict:
    import json

    try:
        out, _ = child.communicate(timeout=CHILD_EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        _stop_child(child)
        raise PeerSilent(f"TCU process did not end within {CHILD_EXIT_TIMEOUT_S:g} s after the run") from None
    lines = [ln for ln in (out or "").splitlines() if ln.startswith("{")]
    if not lines:
        raise PeerSilent(f"TCU process ended with code {child.returncode} without a report")
    return json.loads(lines[-1])


def _summary(scenario, strategy, seed, bus_name, mode, plant: PlantNode, report, path, wall, load) -> dict:
    ps = plant.plant_side
    period = scenario.run.exchange_period_s
    lag = observer_lag_by_step(scenario, ps.truth_t, ps.truth_mu, plant.observer_mu, ps.tracker.serious_time_s)
    det = report.get("detected_step")
    extra = {"observer_lag_ms": lag, "mode": mode, "wall_s": wall, "sim_s": ps.plant.t_s,
             "sim_s_per_wall_s": ps.plant.t_s / wall if wall > 0 else None,
             "bus_load_percent": load["load_percent"], "frames_tx": plant.frames_tx, "frames_rx": plant.frames_rx,
             "rejected_frames": dict(plant.rejected), "tcu_rejected_frames": report.get("rejected_frames", {}),
             "tcu_rejected_readings": report.get("rejected_readings"),
             "tcu_events": report.get("events"), **plant.timing_summary()}
    return clean(summarise(scenario=scenario, strategy=strategy, seed=seed, bus=bus_name, tracker=ps.tracker,
                           events=plant.events, samples_v=np.asarray(report["samples_v"]),
                           samples_mu=np.asarray(report["samples_mu"]),
                           t_detected_s=None if det is None else det * period, mcap_path=path, extra=extra))
