"""The plant node: the plant with its sensors and effects (``PlantRig``), and the frames it sends and
receives on a bus (``PlantNode``).

``PlantRig.sense()`` measures the plant at the current step (true state and sensor reading recorded,
stage tracked in the run's ``Trace``) and ``apply(command)`` advances it one exchange period; the
benches use a rig on its own.  ``PlantNode`` wraps a rig for the bus: it sends ``PlantSensor`` and
heartbeats, and every received frame goes through ``FrameCodec.classify`` and a step-sequence check
before it counts.  Valid TCU frames are recorded decoded (``/tcu/*``) and fed to the ``Trace``
(events, samples, observer); every frame, valid or not, is recorded raw on ``/can/frames`` with its
status.  Rejected frames are counted by reason.  The loop that paces all this is ``hil.exchange``.
On a mapped bus (a TCU's own DBC, ``hil/bus/mapping.py``) the sensor, demand and command travel in
their messages, without step counters: the first command frame after the period's frames answers it.
"""
from __future__ import annotations

import time

import can

from identifier.messages import DriverDemand, SensorReading, TorqueCommand
from plant import SensorModel, WheelsetPlant

from .effects import Reality
from .config import DBC_MOTOR_SPEED_RAD_S, DBC_TRAIN_SPEED_MS
from .errors import NoProgress, PeerSilent, PlantError, ScenarioMismatch, TcuDidNotStart
from .bus.frames import (STATE_FAULT, STATE_RUNNING, STATE_STARTING, TCU_IDS, FrameCodec, RejectCounter,
                         scenario_digest_word)
from .bus.link import Sender, heartbeat_period_s, poll_until, silence_limit_s
from .bus.mapping import codec_for
from .bus.secoc import node_key
from .log.record import (Recorder, write_command, write_estimate, write_frame, write_identification,
                         write_plant_state, write_rail_truth, write_sensor, write_status)
from .traction import TruthTrack
from .trace import Trace
from .bus.verdicts import (ANSWERED_TWICE, BAD_SEQUENCE, DUPLICATE, FOREIGN, FRESH, LATE, NOT_REJECTED, PROBE,
                           REJECTED, kind)

UNMAPPED = "unmapped_id:"          # a mapped bus: a frame of an id the mapping does not name (hil/bus/mapping.py)


#: the longest the plant node writes log rows in line before it looks at the bus again
FLUSH_SLICE_S = 20e-6
#: pacing: a wait ends in the bus this long before its time (a bus may round its timeout up to 1 ms and
#: the scheduler wakes a sleeper late); the rest is polled, sleeping POLL_SLICE_S between polls
WAKE_MARGIN_S = 1.2e-3
POLL_SLICE_S = 50e-6
#: ... and the last SPIN_S are polled without sleeping (a sleeper wakes tens of us late: the period's
#: start would jitter by that; at most this much of each period is spent polling)
SPIN_S = 150e-6
#: real time: in the last QUIET_S before a period's start (at most QUIET_FRACTION of the period) the plant's
#: pacing sends no heartbeat and does no log work: a heartbeat's encoding, MAC, send and row, or a batch of
#: rows pickled for the log's writer, would start the period that much later; both wait for the next period
QUIET_S = 400e-6
QUIET_FRACTION = 0.4
#: a mapped bus's start-up probes (``PlantNode.wait_for_tcu``) go out this often
PROBE_PERIOD_S = 0.05
#: how often the TCU child process is asked whether it still runs (a waitpid at every poll is a
#: syscall on the loop's path; its end is noticed within this, well inside any silence limit)
WATCH_PERIOD_S = 2e-3


class PlantRig:
    """Plant, sensors and effects of one run; ``sense()`` then ``apply(command)`` once per period.

    ``plant``: anything with ``plant.Plant``'s interface (an FMU); default: the CasADi model, or the
    reality plant when the scenario's ``[reality]`` table has plant-level effects."""

    def __init__(self, scenario, seed: int, trace: Trace, recorder: Recorder | None = None, plant=None):
        self.scenario = scenario
        self.reality = Reality(scenario, seed)
        self.plant = plant if plant is not None else (self.reality.plant or WheelsetPlant(scenario.plant_config()))
        self.sensors = self.reality.wrap_sensors(SensorModel(scenario.sensors, seed))
        self.trace = trace
        self.recorder = recorder
        #: the truth the closed-loop metrics judge by (hil/traction.py): never sent to the TCU
        self.truth = TruthTrack(scenario)

    @property
    def step(self) -> int:
        return self.plant.step_index

    @property
    def t_s(self) -> float:
        return self.plant.t_s

    def demand(self) -> DriverDemand:
        """The driver's demand for the current step (the scenario's profile, or the paper's constant one)."""
        return DriverDemand(self.plant.step_index, self.truth.demand_torque_nm(self.plant.t_s))

    def sense(self) -> SensorReading:
        """The reading the TCU gets this period (after any CAN effect); the step's truth is kept."""
        s = self.plant.state
        k = self.plant.step_index
        stage = self.trace.plant(k, s.t_s, s.creep_speed_kmh, s.mu)
        truth = self.truth.add(s, getattr(self.plant, "cleaned", ()))
        omega, v = self.sensors.measure(s.motor_speed_rad_s, s.train_speed_ms)
        if self.recorder:
            write_plant_state(self.recorder, k, s, stage)
            write_sensor(self.recorder, s.t_s, k, omega, v)
            write_rail_truth(self.recorder, k, s.t_s, *truth)
        return self.reality.deliver(SensorReading(k, omega, v))

    def apply(self, command: TorqueCommand) -> None:
        self.plant.step(command.torque_nm)


def describe_exit(process) -> str:
    """How a finished process ended: 'exited with code N' or 'was killed by SIGNAME'."""
    import signal

    code = process.returncode
    if code is not None and code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:  # a signal number Python does not name
            return f"was killed by signal {-code}"
    return f"exited with code {code}"


#: how many of its last stderr lines a dead TCU's message quotes
STDERR_TAIL_LINES = 5


def stderr_tail(process, lines: int = STDERR_TAIL_LINES) -> str:
    """'; its stderr ends: ...' with the last ``lines`` non-empty lines of the file a watched process
    writes its stderr to (``process.stderr_path``, set by whoever started it); '' when there is none."""
    path = getattr(process, "stderr_path", None)
    if not path:
        return ""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            f.seek(max(f.tell() - 8192, 0))
            text = f.read().decode("utf-8", "replace")
    except OSError:  # no stderr file: nothing to quote
        return ""
    tail = [line.rstrip() for line in text.splitlines() if line.strip()][-lines:]
    return f"; its stderr ends: {' | '.join(tail)}" if tail else "; its stderr is empty"


class PlantNode:
    """A rig on a bus: sends sensor frames and heartbeats, receives everything, records it.

    ``watch``: the TCU's process (``Popen``) when this run started it, so its death is noticed at
    once; ``watch_silence``: apply the silence limit (not for the in-process node, which cannot be
    silent)."""

    def __init__(self, rig: PlantRig, bus: can.BusABC, mode: str, *, strategy: str, watch=None,
                 watch_silence: bool = True):
        scenario = rig.scenario
        self.rig = rig
        self.trace = rig.trace
        self.rec = rig.recorder
        self.period_s = scenario.run.exchange_period_s
        self.codec = codec_for(scenario, self.period_s, auth=node_key(scenario.bus))
        self._plain_codec = FrameCodec(self.period_s, self.codec.db)     # checks own frames, no freshness
        #: a TCU's own DBC (hil/bus/mapping.py): no step counters, the first command after the period's frames counts
        self.mapped = getattr(self.codec, "mapped", False)
        self.tcu_ids = TCU_IDS | (self.codec.tcu_ids if self.mapped else set())
        #: mapped: frames of ids the mapping does not name, by id ("0x300" -> count)
        self.unmapped: dict[str, int] = {}
        self._new_command: TorqueCommand | None = None    # mapped: the command that answers the period
        self._waiting = False                              # mapped: between the period's frames and its deadline
        self._started = False                              # mapped: step 0's frames went out (probes before)
        self.bus = bus
        self.sender = Sender(bus)
        self.mode = mode
        self.settings = scenario.bus
        self.strategy = strategy
        self.watch = watch
        self._next_watch = 0.0       # time.monotonic() of the next look at the TCU child
        self.watch_silence = watch_silence
        self.silence_s = silence_limit_s(self.settings, mode, self.period_s)
        self.progress_s = self.settings.lockstep_progress_s if mode == "lockstep" else None
        self.spin_s = self.settings.lockstep_spin_s if mode == "lockstep" else 0.0
        self.heartbeat_s = heartbeat_period_s(self.settings, mode)
        self.quiet_s = min(QUIET_S, QUIET_FRACTION * self.period_s)
        self.rejected = RejectCounter()
        self.commands: dict[int, TorqueCommand] = {}
        self.awaited = -1
        self.last_status_step = -1
        self.last_result_step = -1
        self.last_sample_index = -1
        self.last_estimate_step = -1
        self.tcu_state: int | None = None
        self.tcu_step: int | None = None       # the last step the TCU's heartbeat says it took
        self._sensor_msg: can.Message | None = None
        self.last_tcu_rx: float | None = None
        self.frames_tx = 0
        self.frames_rx = 0
        self.late_commands = 0
        self.answered = bytearray()            # answered[k]: a command for step k was taken
        self.suspicious: dict[str, int] = {}   # what the stream itself shows to be wrong (no authentication)
        self.fault_time_s = scenario.run.fault_time_s
        self.hb_counter = 0
        self.next_hb = 0.0
        self.scenario_digest = scenario.digest
        self.tcu_digest: int | None = None     # the TcuScenario frame's word: the scenario the TCU says it runs

    @property
    def t_s(self) -> float:
        return self.rig.t_s

    # -- sending -----------------------------------------------------------------------------
    def send(self, msg: can.Message) -> None:
        msg.timestamp = time.time()
        self.sender.send(msg)
        self.frames_tx += 1
        if self.rec:
            write_frame(self.rec, self.t_s, msg, "tx", FRESH, time.time_ns())

    def send_sensor(self) -> None:
        """Send the driver's demand, sense the plant at its current step and send the reading; that step's
        command is awaited."""
        self.awaited = self.rig.step
        if self.mapped:
            demand = self.rig.demand()
            self._sensor_reading = self.rig.sense()
            self._new_command, self._waiting, self._started = None, True, True
            for msg in self.codec.sensor_frames(demand, self._sensor_reading):
                self.send(msg)
            return
        self.send(self.codec.demand(self.rig.demand()))
        self._sensor_reading = self.rig.sense()
        self._check_range(self._sensor_reading)
        self._sensor_msg = self.codec.sensor(self._sensor_reading)
        self.send(self._sensor_msg)

    def _check_range(self, reading: SensorReading) -> None:
        """A reading the PlantSensor frame cannot carry ends the run here, saying why: the TCU would reject
        it (``out_of_range``) and a lockstep run would wait ``2 x lockstep_progress_s`` to end as a silent
        TCU.  Two comparisons a period."""
        if abs(reading.motor_speed_rad_s) > DBC_MOTOR_SPEED_RAD_S or abs(reading.train_speed_ms) > DBC_TRAIN_SPEED_MS:
            raise PlantError(f"{self.rig.scenario.path}: at t = {self.t_s:.4f} s the measured speeds (motor "
                             f"{reading.motor_speed_rad_s:.1f} rad/s, train {reading.train_speed_ms:.2f} m/s) leave "
                             f"the PlantSensor frame's range (+-{DBC_MOTOR_SPEED_RAD_S:g} rad/s, "
                             f"+-{DBC_TRAIN_SPEED_MS:g} m/s, hil/hil.dbc): the wheel ran away (control law "
                             f"{self.rig.scenario.control.law}); shorten run.duration_s or let a control law "
                             "hold the creep")

    def resend_sensor(self) -> None:
        """The pending step's reading once more (lockstep progress deadline, ``await_command``), in a
        new frame: with authentication the same frame again would be a replay."""
        self._sensor_msg = self.codec.sensor(self._sensor_reading)
        self.send(self._sensor_msg)

    def heartbeat(self, state: int) -> None:
        self.send(self.codec.plant_heartbeat(self.hb_counter, state, max(self.awaited, 0)))
        self.hb_counter += 1

    def heartbeat_if_due(self, now: float) -> None:
        if now >= self.next_hb:
            self.heartbeat(STATE_RUNNING)
            self.next_hb += self.heartbeat_s
            if self.next_hb <= now:           # fell behind (or the first one): restart the schedule
                self.next_hb = now + self.heartbeat_s

    def finish(self, state: int) -> None:
        """Tell the TCU the run is over (finished or fault); it then reports and exits."""
        for _ in range(2):
            try:
                self.heartbeat(state)
            except Exception:  # noqa: BLE001 - the bus may be gone on an abort
                return

    # -- receiving ---------------------------------------------------------------------------
    def on_rx(self, msg: can.Message) -> None:
        wall_ns = time.time_ns()
        self.frames_rx += 1
        frame, status = self.codec.classify(msg)
        if frame is not None:
            status = self._accept(frame)
        if status not in NOT_REJECTED and kind(status) == REJECTED:
            self.rejected[status] += 1
        elif status.startswith(UNMAPPED):
            key = status[len(UNMAPPED):]
            self.unmapped[key] = self.unmapped.get(key, 0) + 1
        elif msg.arbitration_id in self.tcu_ids:
            self.last_tcu_rx = time.monotonic()
        if self.rec:
            write_frame(self.rec, self.t_s, msg, "rx", status, wall_ns)

    def _accept(self, frame) -> str:
        """Sequence checks of a decoded frame (its verdict, ``hil/bus/verdicts.py``); FRESH records and traces it."""
        name, v, rec, current = frame.name, frame.value, self.rec, self.awaited
        if name == "TorqueCommand" and self.mapped:
            return self._accept_mapped_command(v)
        if name == "TcuFrame":               # mapped: the TCU's other messages (tcu_frames): logged, not acted on
            return FRESH
        if name == "TorqueCommand":
            if v.step < current:
                if v.step < len(self.answered) and self.answered[v.step]:
                    self.notice("answered_twice", f"a second TorqueCommand for step {v.step}, already answered")
                    return ANSWERED_TWICE
                self.late_commands += 1
                return LATE
            if v.step > current:
                return BAD_SEQUENCE
            if v.step in self.commands:      # the first one stays
                self.notice("duplicate_command", f"a second TorqueCommand for the pending step {v.step}")
                return DUPLICATE
            if v.step >= len(self.answered):
                self.answered.extend(bytes(max(v.step + 1 - len(self.answered), 4096)))
            self.answered[v.step] = 1
            self.commands[v.step] = v
            if rec:
                write_command(rec, v, self.period_s)
            return FRESH
        if name == "TcuStatus":
            st, obs = v
            if not (self.last_status_step < st.step <= current):
                return BAD_SEQUENCE
            self.last_status_step = st.step
            self.trace.observer(obs)
            self.settle_results(st.step)
            if rec:
                write_status(rec, st, obs, self.period_s)
            return FRESH
        if name == "TcuResult":
            if not (self.last_result_step <= v.step <= current):
                return BAD_SEQUENCE
            self.last_result_step = v.step
            if v.t_s < self.fault_time_s:
                self.notice("result_before_fault", f"an identification result ({v.kind}) at t = {v.t_s:.4f} s, "
                            f"before the fault at {self.fault_time_s:g} s")
            self.trace.result(v)
            return FRESH
        if name == "TcuInterval":
            return FRESH if self.trace.interval(v) else BAD_SEQUENCE
        if name == "TcuEstimate":
            if not (self.last_estimate_step <= v.step <= current):
                return BAD_SEQUENCE
            self.last_estimate_step = v.step
            self.trace.estimate(v)
            if rec:
                write_estimate(rec, v)
            return FRESH
        if name == "TcuSample":
            if v.index != self.last_sample_index + 1 or not (0 <= v.step <= current):
                return BAD_SEQUENCE
            self.last_sample_index = v.index
            self.trace.sample(v.creep_speed_kmh, v.mu_hat)
            self.trace.detected(v.detected_step)
            return FRESH
        if name == "TcuHeartbeat":
            if v.step > max(current, 0):
                self.notice("heartbeat_ahead", f"a TCU heartbeat at step {v.step}, past the plant's step {current}")
            self.tcu_state = v.state
            self.tcu_step = v.step
            return FRESH
        if name == "TcuScenario":
            self.tcu_digest = v
            return FRESH
        if name in ("PlantSensor", "DriverDemand"):
            self.notice("sensor_from_another_node", f"a {name} frame for step {v.step} this plant did not send")
        return FOREIGN        # plant frames from another node on the bus

    def _accept_mapped_command(self, v: TorqueCommand) -> str:
        """A command frame of a mapped bus (no step counter): the first one while the plant waits in a period
        (from its frames to the command or the deadline) answers that period; any other is late (after the
        deadline, or a second one that period); before the run (the start-up probes' answers) it is a sign
        of life only."""
        if not self._started:
            return PROBE
        if not self._waiting or self._new_command is not None:
            self.late_commands += 1
            return LATE
        self._new_command = TorqueCommand(self.awaited, v.torque_nm)
        if self.rec:
            write_command(self.rec, self._new_command, self.period_s)
        return FRESH

    def notice(self, what: str, text: str) -> None:
        """Count something the stream shows to be wrong (a third node on the bus, a replay); the first of
        each kind also goes to the log as a warning event."""
        n = self.suspicious.get(what, 0)
        self.suspicious[what] = n + 1
        if n == 0 and self.rec:
            self.rec.event(self.t_s, "WARN", f"suspicious frame ({what}): {text}; another node on the bus?")

    def settle_results(self, upto_step: int | None = None) -> None:
        """Results up to ``upto_step`` (all: None) are final (their intervals came first): record them."""
        for e in self.trace.settle(upto_step):
            if self.rec:
                write_identification(self.rec, e, self.strategy)

    def poll(self, until: float | None, log_work: bool = True) -> None:
        """Receive one frame, or wait at most until ``until`` (perf_counter) or the next heartbeat.

        While nothing has arrived it gives the log its due (``Recorder.work``: a batch of rows shipped
        to the writer process, or queued rows written in line in slices of at most ``FLUSH_SLICE_S``),
        so the log costs the loop nothing between a deadline and the sensor frame; not with
        ``log_work`` False (real time's wait for the command: a batch's pickling and pipe write would
        come on top of the round trip whenever the command arrives during it; the rest of the period
        has room for it); nor in real time's last ``quiet_s`` before a period starts (``QUIET_S``), where no
        heartbeat goes out either.
        With nothing to do for the log, lockstep polls the bus for up to ``[bus] lockstep_spin_s``
        before it sleeps in it: the TCU's answer then finds this process awake (a sleeper's wake-up
        costs tens of us a frame, and lockstep runs as fast as the bus allows)."""
        now = time.perf_counter()
        # real time's pacing, close to the period's start: nothing but the bus (QUIET_S)
        quiet = log_work and until is not None and until - now < self.quiet_s
        if not quiet:
            self.heartbeat_if_due(now)
        timeout = self.next_hb - now
        if until is not None:
            timeout = until - now if quiet else min(timeout, until - now)
        msg = None
        if log_work and not quiet and self.rec is not None and self.rec.work_due:
            msg = self.bus.recv(timeout=0.0)
            if msg is None:
                self.rec.work(now + max(min(FLUSH_SLICE_S, timeout), 0.0))
            timeout = None
        elif until is None and self.spin_s > 0.0:
            # lockstep: poll a while first (waking a sleeper costs tens of us a frame), then sleep
            msg = poll_until(self.bus, now + min(self.spin_s, max(timeout, 0.0)))
            timeout = self.next_hb - time.perf_counter()
        if msg is None and timeout is not None:
            if timeout > WAKE_MARGIN_S:     # sleep in the bus until shortly before the time ...
                msg = self.bus.recv(timeout=min(timeout - WAKE_MARGIN_S, self.silence_s / 4))
            else:                           # ... then poll, yielding the CPU between polls, all but SPIN_S
                msg = self.bus.recv(timeout=0.0)
                if msg is None and timeout > SPIN_S:
                    time.sleep(min(timeout - SPIN_S, POLL_SLICE_S))
        if msg is not None:
            self.on_rx(msg)
        self.check_alive()

    def drain(self) -> None:
        """Record what is still queued."""
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            self.on_rx(msg)
        self.settle_results()

    def drain_until(self, done, timeout_s: float) -> None:
        """Record the TCU's last frames until ``done()`` or ``timeout_s``."""
        end = time.monotonic() + timeout_s
        while not done() and time.monotonic() < end:
            msg = self.bus.recv(timeout=0.01)
            if msg is not None:
                self.on_rx(msg)
        self.drain()

    # -- liveness ------------------------------------------------------------------------------
    def check_alive(self) -> None:
        if self.watch is not None and (now := time.monotonic()) >= self._next_watch:
            self._next_watch = now + WATCH_PERIOD_S
            if self.watch.poll() is not None:
                if self.last_tcu_rx is None:      # it never joined: the set-up's fault (a typo, a missing module)
                    raise TcuDidNotStart(f"the TCU process {describe_exit(self.watch)} before it joined the bus"
                                         f"{stderr_tail(self.watch)}")
                raise PeerSilent(f"the TCU process {describe_exit(self.watch)} at step {self.awaited}, "
                                 f"t = {self.t_s:.4f} s (a crash){stderr_tail(self.watch)}")
        if self.tcu_state == STATE_FAULT:
            raise PeerSilent(f"TCU reported a fault at step {self.awaited}")
        if not self.watch_silence or self.last_tcu_rx is None:
            return
        quiet = time.monotonic() - self.last_tcu_rx
        if quiet > self.silence_s:
            if self.watch is not None and self.watch.poll() is not None:
                self._next_watch = 0.0
                self.check_alive()         # it died: said as a crash, with its exit code
            how = ("; its process still runs (a freeze, not a crash)" if self.watch is not None else "")
            raise PeerSilent(f"TCU silent for {quiet * 1e3:.1f} ms (limit {self.silence_s * 1e3:.1f} ms) at step "
                             f"{self.awaited}, t = {self.t_s:.4f} s{how}")

    def wait_for_tcu(self) -> None:
        """Heartbeats 'starting' until the TCU shows up.  On a mapped bus a TCU of another make sends no
        heartbeat and waits for readings: the plant also sends its frames of the state at the start (no
        noise; *probes*) every ``PROBE_PERIOD_S`` until a command frame answers; the built-in TCU
        ignores probes (it starts counting readings at the 'running' heartbeat sent here before step 0)."""
        t0 = time.monotonic()
        next_probe = time.perf_counter() + PROBE_PERIOD_S    # a TCU already there answers the heartbeat first
        while self.last_tcu_rx is None:
            if time.monotonic() - t0 > self.settings.startup_timeout_s:
                alive = "; its process still runs (no frame from it: a freeze, or a bus it did not open)" \
                    if self.watch is not None else ""
                raise PeerSilent(f"no TCU answered within {self.settings.startup_timeout_s:g} s{alive}")
            now = time.perf_counter()
            if now >= self.next_hb:
                self.heartbeat(STATE_STARTING)
                self.next_hb = now + min(self.heartbeat_s, 0.05)
            if self.mapped and now >= next_probe:
                s = self.rig.plant.state
                for msg in self.codec.sensor_frames(self.rig.demand(), SensorReading(0, s.motor_speed_rad_s,
                                                                                     s.train_speed_ms)):
                    self.send(msg)
                next_probe = now + PROBE_PERIOD_S
            msg = self.bus.recv(timeout=min(self.heartbeat_s, 0.05))
            if msg is not None:
                self.on_rx(msg)
            self.check_alive()
        self._check_scenario()

    def _check_scenario(self) -> None:
        """The TCU runs this scenario, or the run stops here, before the first period: a TCU that
        announces its scenario (TcuScenario, right before each of its heartbeats until the first reading)
        with another digest is a ``ScenarioMismatch`` naming both.  A TCU heard without its announcement
        gets a few heartbeat periods to send it (its first one may have gone out before this bus was
        open); a TCU that never sends one (another make's) is not checked."""
        if self.tcu_digest is None and not self.mapped:
            until = time.monotonic() + max(3 * self.heartbeat_s, 0.02)
            while self.tcu_digest is None and time.monotonic() < until:
                msg = self.bus.recv(timeout=max(until - time.monotonic(), 0.0))
                if msg is not None:
                    self.on_rx(msg)
            self.check_alive()
        mine = scenario_digest_word(self.scenario_digest)
        if self.tcu_digest is not None and self.tcu_digest != mine:
            raise ScenarioMismatch(f"the TCU runs another scenario: its digest {self.tcu_digest:016x}, this "
                                   f"plant's {mine:016x} ({self.rig.scenario.path}); start both on the same "
                                   "scenario file with the same --set items")

    def begin(self) -> None:
        """Right before step 0: on a mapped bus a 'running' heartbeat, from which the built-in TCU counts
        readings (without step counters, its steps are the plant's only when both start together)."""
        if self.mapped:
            self.heartbeat(STATE_RUNNING)
            self.next_hb = time.perf_counter() + self.heartbeat_s

    def await_command(self, k: int, deadline: float | None) -> TorqueCommand | None:
        """The TCU's command for step ``k``, or None when ``deadline`` (perf_counter) passes first.

        Lockstep (no deadline): when ``progress_s`` wall seconds pass without the command while the TCU
        lives, the sensor frame is sent once more; after ``progress_s`` more, ``NoProgress`` (exit 3)
        names the step and the likely cause."""
        if self.mapped:
            return self._await_mapped(k, deadline)
        give_up = resent = None
        if deadline is None and self.progress_s is not None:
            give_up, resent = time.monotonic() + self.progress_s, False
        rejected_before = dict(self.rejected)
        while k not in self.commands:
            if deadline is not None and time.perf_counter() >= deadline:
                return None
            self.poll(deadline, log_work=deadline is None)
            if give_up is not None and k not in self.commands and time.monotonic() > give_up:
                if resent:
                    cause = self._no_progress_cause(k, rejected_before)
                    raise NoProgress(f"no command for step {k} within {2 * self.progress_s:g} s although the TCU "
                                     f"is alive (its sensor frame sent twice): {cause}")
                self.resend_sensor()
                give_up, resent = time.monotonic() + self.progress_s, True
        return self.commands.pop(k)

    def _await_mapped(self, k: int, deadline: float | None) -> TorqueCommand | None:
        """``await_command`` on a mapped bus: the first command frame after the period's frames, or None at
        the deadline (real time).  Lockstep waits for it as long as the TCU needs; a frame cannot be sent
        again there (without step counters it would be a new reading), so after twice
        ``lockstep_progress_s`` ``NoProgress`` ends the run."""
        give_up = time.monotonic() + 2 * self.progress_s if deadline is None and self.progress_s is not None else None
        try:
            while self._new_command is None:
                if deadline is not None and time.perf_counter() >= deadline:
                    return None
                self.poll(deadline, log_work=deadline is None)
                if give_up is not None and self._new_command is None and time.monotonic() > give_up:
                    raise NoProgress(f"no command frame ({self.codec.mapping.command_message.name}) for step {k} "
                                     f"within {2 * self.progress_s:g} s although the TCU is alive")
            return self._new_command
        finally:
            self._waiting = False
            self._new_command = None

    def _no_progress_cause(self, k: int, rejected_before: dict) -> str:
        """The likely reason step ``k`` got no command: the sensor frame itself (the TCU validates it
        against the DBC as this side can), the TCU's heartbeat step, the frames rejected here."""
        frame, status = self._plain_codec.classify(self._sensor_msg)
        if frame is None:
            reason, _, signal = status.partition(":")
            m = self.codec.db.get_message_by_frame_id(self._sensor_msg.arbitration_id)
            value = m.decode(bytes(self._sensor_msg.data), decode_choices=False).get(signal) if signal else None
            if reason == "out_of_range":
                s = m.get_signal_by_name(signal)
                return (f"TCU rejected the sensor frame: {signal} {value:.6g} is out of the DBC range "
                        f"[{s.minimum:g}, {s.maximum:g}]")
            if reason == "non_finite":
                return f"TCU rejected the sensor frame: {signal} is {value}, not a finite number"
            return f"TCU rejected the sensor frame: {status}"
        new = {r: n - rejected_before.get(r, 0) for r, n in self.rejected.items() if n > rejected_before.get(r, 0)}
        here = (" (frames rejected here meanwhile: " + ", ".join(f"{r} x{n}" for r, n in sorted(new.items())) + ")"
                if new else "")
        if self.tcu_step is None:
            return f"no command for step {k}{here}"
        if self.tcu_step > k:
            return (f"the TCU's heartbeat says it is at step {self.tcu_step}, past the plant's step {k}: it took a "
                    f"sensor frame this plant did not send (another node on the bus?) and now rejects the plant's "
                    f"frames as out of sequence{here}")
        if self.tcu_step == k:
            return f"the TCU took step {k} but its command did not arrive or was rejected here{here}"
        return f"the TCU's heartbeat says its last step is {self.tcu_step}: the sensor frame of step {k} did not " \
               f"reach it or was rejected there{here}"

    def counters(self) -> dict:
        mapped = {"unmapped_ids": dict(sorted(self.unmapped.items())),
                  "out_of_range_signals": dict(sorted(self.codec.out_of_range.items()))} if self.mapped else {}
        return {"frames_tx": self.frames_tx, "frames_rx": self.frames_rx, "rejected_frames": dict(self.rejected),
                "late_commands": self.late_commands, "suspicious": dict(self.suspicious), **mapped}
