"""Offline re-identification of a recorded run: ``hil replay``.

The identifier is fed what the TCU received: the plant's sensor frames, decoded through the DBC by
the same ``TcuNode`` the TCU process runs (same validation and step sequencing), as fast as the
machine allows.  Sources, in order of preference:

- an MCAP log of ``hil run``: the raw ``/can/frames`` (the plant's transmitted ``PlantSensor``
  frames); a log with no frames (older in-process runs) falls back to ``/plant/sensor``, encoded to
  frames by the DBC (64-bit floats, so exactly the readings).  The scenario comes from the log's
  ``scenario`` metadata (or ``--scenario``), strategy and seed from its ``run`` metadata;
- a mapped run's log (``[bus] dbc``, ``hil/bus/mapping.py``): the plant's frames on its DBC, which the log
  keeps, decoded by the same ``MappedCodec``, and its heartbeats (the built-in TCU counts readings from
  the 'running' one, so the start-up probes are passed over as in the run);
- a CAN log of another tool (``.log`` candump, ``.asc``, ``.blf``, ... anything ``can.LogReader``
  reads) with ``--scenario``.

The summary is the one ``hil run --json`` prints (``hil.trace.Trace``), with the stages from
the logged true plant state when present, plus ``matches_log`` (the replayed identification events
equal the logged ones: count, kind, correction number and step exactly, parameters to ``PARAMS_RTOL``
(the compiled kernels' last bits depend on the CPU they were built for); ``None``
when the strategy or seed differ from the logged run's, or the log holds no identification record)
and ``messages_read``.  A damaged log (run killed, file cut, bytes changed) replays what survived
(``hil.log.read`` skips damaged chunks); ``damage`` says what was lost and where.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import can

from identifier import DEFAULT_STRATEGY
from identifier.messages import IdentificationEvent, SensorReading

from .config import load_scenario
from .errors import LogError
from .bus.frames import DEMAND_ID, PLANT_HEARTBEAT_ID, RESULT_ID, SENSOR_ID, FrameCodec
from .bus.mapping import codec_for
from .log.read import MAGIC, read_log, scenario_from_log
from .tcu_node import TcuNode
from .trace import Trace, clean

#: file suffixes read with ``can.LogReader`` (python-can's writers/readers)
CAN_LOG_SUFFIXES = (".log", ".asc", ".blf", ".csv", ".trc", ".mf4")
#: the option a closed-loop log recorded before gp dated changes of rail is replayed with (``load_mcap``)
GP_RAIL_CHANGES_OFF = "identifier.options.gp.rail_changes"
#: behaviour newer than some logs: (the key of the log's ``run`` metadata that marks a log recorded with it, the
#: law it concerns, None for any closed-loop law or ``EVERY_RUN`` for open-loop runs too, the ``--set``
#: overrides that replay a log without it as it ran).  A law's commands do not reach a replay (the logged
#: torques do), but its requests to re-arm the identifier do, so the law must run as it did.
EVERY_RUN = "*"
NEWER_THAN_SOME_LOGS = (
    ("gp_rail_changes", None, {GP_RAIL_CHANGES_OFF: False}),
    ("identified_rail_climb", "identified", {"control.options.identified.change_mu": 0.0,
                                             "control.options.identified.dither_kmh": 0.08,
                                             "control.options.identified.gain": 300.0}),
    ("identified_past_a_peak", "identified", {"control.options.identified.past_slope": 0.0}),
    ("identified_rise", "identified", {"control.options.identified.rise_mu": 0.0}),
    ("identified_peak_estimate", "identified", {"control.options.identified.blind": 1,
                                                "control.options.identified.cap_kmh": 0.7,
                                                "control.options.identified.max_kmh": 1.6,
                                                "control.options.identified.drop_fraction": 1.0,
                                                "control.options.identified.change_limited": 0,
                                                "control.options.identified.startup_s": 0.0}),
    ("identified_relative_drop", "identified", {"control.options.identified.drop_ratio": 0.0,
                                                "control.options.identified.settle_s": 0.0,
                                                "control.options.identified.centre_median": 0,
                                                "control.options.identified.lift": 0,
                                                "control.options.identified.jump_width": 2.0,
                                                "control.options.identified.ceiling_width": 4.0}),
    # (before identified_creep_bounds: a log older than both ran with that entry's bounds, so it must win)
    ("identified_creep_bounds", "identified", {"control.options.identified.max_kmh": 12.0,
                                               "control.options.identified.cap_kmh": 0.75}),
    # the peak estimate's memory and hazard per update since 2026-11-29 (they ran per period, five times longer:
    # memory_s 1.5 and hazard_s 10 in today's units give the constants of then exactly); only a law acting on the
    # estimate (an option of ``identified``'s, or the first issue-50 merge's defaults) moves with them
    ("peak_estimate_per_update", "identified", {"identifier.options.peak_estimate.memory_s": 1.5,
                                                "identifier.options.peak_estimate.hazard_s": 10.0}),
    ("gp_closed_loop_tracking", None, {"identifier.options.gp.track_train_speed": False,
                                       "identifier.options.gp.floor_peak_mu": 0.0,
                                       "identifier.options.gp.floor_peak_creep_kmh": 0.0}),
    ("gp_open_loop_edge", EVERY_RUN, {"identifier.options.gp.open_loop_edge": False}),
    # gp's closed-loop confirmation refused from a window that does not hold one rail (2026-11-29, issue 50)
    ("gp_one_rail", None, {"identifier.options.gp.one_rail": False}),
)
#: topics a replay reads from an MCAP log
REPLAY_TOPICS = {"/can/frames", "/plant/sensor", "/plant/state", "/tcu/identification", "/tcu/status"}


@dataclass
class ReplaySource:
    """What a replay needs from a log, whatever its format."""
    path: str
    kind: str                                   # "mcap-frames" | "mcap-sensor" | "can-log"
    scenario: object
    frames: list                                # can.Message, in bus order (sensor frames at least)
    logged_strategy: str | None = None
    logged_seed: int | None = None
    logged_events: list | None = None           # (step, kind, correction, params) or None: nothing to compare
    logged_last_step: int | None = None         # events up to this step are complete in the log
    truth: list = field(default_factory=list)   # (t_s, creep_speed_kmh, mu) of the true plant state
    messages_read: int = 0
    complete: bool = True
    codec: object = None                        # a mapped run's codec (hil/bus/mapping.py); None: hil/hil.dbc
    damage: str = ""
    ended_early: str = ""                       # a log closed properly whose run did not finish: why


def _msg_from_record(r) -> can.Message:
    return can.Message(timestamp=r.send_time_ns * 1e-9, arbitration_id=r.arbitration_id,
                       is_extended_id=r.is_extended_id, is_fd=r.is_fd, bitrate_switch=r.bitrate_switch,
                       is_error_frame=r.is_error_frame, is_remote_frame=r.is_remote_frame, dlc=r.dlc,
                       data=bytes(r.data), check=False)


def _named_in(scenario, key: str) -> bool:
    """Whether the scenario itself sets the option ``key`` (``control.options.LAW.NAME`` or
    ``identifier.options.STRATEGY.NAME``): an option it names ran as named, whatever the default of then."""
    parts = key.split(".")
    if len(parts) != 4 or parts[1] != "options":
        return False
    tables = {"control": scenario.control.options, "identifier": scenario.identifier.get("options", {})}
    return parts[3] in (tables.get(parts[0]) or {}).get(parts[2], {})


def load_mcap(path, scenario_file=None) -> ReplaySource:
    log = read_log(path, topics=REPLAY_TOPICS)
    scenario = (load_scenario(scenario_file) if scenario_file is not None
                else scenario_from_log(log, "; give the scenario with --scenario FILE"))
    run = log.metadata.get("run") or {}
    as_recorded = {}
    if run:
        closed = scenario.control.law != "demand"
        for key, law, overrides in NEWER_THAN_SOME_LOGS:
            if key not in run and (law == EVERY_RUN or closed and law in (None, scenario.control.law)):
                as_recorded.update({k: v for k, v in overrides.items() if not _named_in(scenario, k)})
    if as_recorded:           # a log recorded before some of today's behaviour: replayed as it ran
        scenario = scenario_from_log(log, overrides=as_recorded) if scenario_file is None else \
            load_scenario(scenario_file, as_recorded)
    try:
        seed = int(run["seed"]) if "seed" in run else None
    except ValueError:  # a seed the log does not hold as a number: replayed unseeded
        seed = None
    frames, sensor, truth, events, status_steps = [], [], [], [], []
    has_ident_topic = False
    upgrade = FrameCodec(scenario.run.exchange_period_s).upgrade     # frames of logs before the trailer
    codec, ids = None, (SENSOR_ID, DEMAND_ID)
    if scenario.bus.dbc:      # a TCU's own DBC: its frames (the log keeps the DBC) and the plant's heartbeats,
        codec = codec_for(scenario, dbc_text=(log.metadata.get("dbc") or {}).get("text"))   # whose 'running'
        ids = codec.plant_ids | {PLANT_HEARTBEAT_ID}                                      # starts the count
    for topic, _, m in log.messages:
        if topic == "/can/frames":
            if m.direction == "tx" and m.arbitration_id in ids and not m.is_extended_id:
                frames.append(upgrade(_msg_from_record(m)))
        elif topic == "/plant/sensor":
            sensor.append(SensorReading(int(m.step), m.motor_speed_rad_s, m.train_speed_ms))
        elif topic == "/plant/state":
            truth.append((m.t_s, m.creep_speed_kmh, m.mu))
        elif topic == "/tcu/identification":
            has_ident_topic = True
            events.append((int(m.step), m.kind, int(m.correction), tuple(m.params)))
        elif topic == "/tcu/status":
            status_steps.append(int(m.step))
    kind = "mcap-frames"
    if not frames and codec is None:
        if not sensor:
            what = f"damaged ({log.damage}) before any" if log.damage else "no"
            raise LogError(f"{path}: {what} sensor data (no PlantSensor frames on /can/frames, no /plant/sensor)")
        codec = FrameCodec(scenario.run.exchange_period_s)
        frames = [codec.sensor(r) for r in sensor]
        kind = "mcap-sensor"
    compare = has_ident_topic or bool(status_steps)
    src = ReplaySource(str(path), kind, scenario, frames, logged_strategy=run.get("strategy"), logged_seed=seed,
                       logged_events=events if compare else None, truth=truth,
                       messages_read=log.message_count, complete=log.complete, damage=log.damage,
                       ended_early=log.ended_early, codec=codec)
    if not log.complete:
        # a cut log: results and status of the last steps may be missing; compare up to the last status - 1
        src.logged_last_step = (max(status_steps) - 1) if status_steps else -1
    return src


def load_can_log(path, scenario_file) -> ReplaySource:
    if scenario_file is None:
        raise LogError(f"{path}: a CAN log has no scenario; give it with --scenario FILE")
    scenario = load_scenario(scenario_file)
    codec = FrameCodec(scenario.run.exchange_period_s)
    frames, events, n = [], [], 0
    damage = ""
    try:
        with can.LogReader(str(path)) as reader:
            for msg in reader:
                n += 1
                if msg.arbitration_id in (SENSOR_ID, DEMAND_ID) and not msg.is_extended_id:
                    frames.append(codec.upgrade(msg))
                elif msg.arbitration_id == RESULT_ID and not msg.is_extended_id:
                    frame, status = codec.classify(codec.upgrade(msg))
                    if frame is not None:
                        e = frame.value
                        events.append((e.step, e.kind, e.correction, tuple(e.params)))
    except ValueError as e:
        if n == 0:
            raise LogError(f"{path}: not a CAN log python-can can read: {e}") from None
        damage = f"unreadable after {n} frames: {e}"
    except Exception as e:  # noqa: BLE001 - a damaged file from another tool: keep what was read
        if n == 0:
            raise LogError(f"{path}: not a CAN log python-can can read ({type(e).__name__}: {e})") from None
        damage = f"unreadable after {n} frames ({type(e).__name__}: {e})"
    if not frames:
        raise LogError(f"{path}: no PlantSensor frames (id 0x{SENSOR_ID:X}) among its {n} frames")
    src = ReplaySource(str(path), "can-log", scenario, frames, logged_events=events if events else None,
                       messages_read=n, complete=not damage, damage=damage)
    if damage:
        src.logged_last_step = max((e[0] for e in events), default=-1)
    return src


def load_source(path, scenario_file=None) -> ReplaySource:
    p = Path(path)
    try:
        with p.open("rb") as f:
            head = f.read(len(MAGIC))
    except OSError as e:
        raise LogError(f"{path}: cannot read: {e.strerror}") from None
    if head == MAGIC or p.suffix.lower() == ".mcap":
        return load_mcap(path, scenario_file)
    if p.suffix.lower() in CAN_LOG_SUFFIXES:
        return load_can_log(path, scenario_file)
    raise LogError(f"{path}: neither an MCAP log (no MCAP magic) nor a CAN log python-can reads "
                   f"({', '.join(CAN_LOG_SUFFIXES)})")


def _event_key(e: IdentificationEvent):
    return (e.step, e.kind, e.correction, tuple(e.params))


#: parameters equal to this relative tolerance count as the same identification: the compiled
#: kernels (identifier/kernels.py) are built for the machine's CPU with reassociated sums, so a log
#: replayed on another CPU class may differ in the last bits
PARAMS_RTOL = 1e-9


def events_match(replayed: list, logged: list) -> bool:
    """Same count, step, kind and correction number, parameters equal to ``PARAMS_RTOL``."""
    if len(replayed) != len(logged):
        return False
    for a, b in zip(replayed, logged):
        if a[:3] != tuple(b[:3]) or len(a[3]) != len(b[3]):
            return False
        if any(not (x == y or abs(x - y) <= PARAMS_RTOL * max(abs(x), abs(y))) for x, y in zip(a[3], b[3])):
            return False
    return True


def replay(src: ReplaySource, strategy: str | None = None, seed: int | None = None) -> dict:
    """Re-run the identifier on ``src``; the ``hil run --json`` summary plus replay fields."""
    scenario = src.scenario
    strategy = strategy or src.logged_strategy or DEFAULT_STRATEGY
    seed = seed if seed is not None else (src.logged_seed if src.logged_seed is not None else scenario.run.seed)
    period = scenario.run.exchange_period_s
    # the logged frames' MACs are of the run's key and freshness: a replay reads them unauthenticated
    node = TcuNode(scenario, strategy, seed, codec=src.codec or FrameCodec(period))
    trace = Trace(scenario)
    for t_s, creep, mu in src.truth:
        trace.plant(int(round(t_s / period)), t_s, creep, mu)
    codec = node.codec
    wall0 = time.perf_counter()
    for msg in src.frames:
        for reply in node.handle(msg):      # the frames the TCU would send, read back as the plant reads them
            frame, _ = codec.classify(reply)
            if frame is None:
                continue
            if frame.name == "TcuResult":
                trace.result(frame.value)
            elif frame.name == "TcuInterval":
                trace.interval(frame.value)
            elif frame.name == "TcuSample":
                trace.sample(frame.value.creep_speed_kmh, frame.value.mu_hat)
                trace.detected(frame.value.detected_step)
            elif frame.name == "TcuStatus":
                trace.observer(frame.value[1])
                trace.settle(frame.value[0].step)
    wall = time.perf_counter() - wall0
    trace.detected(node.identifier.detector.detected_step)
    trace.settle()

    # compare with the logged identification when it came from the same strategy and seed (a CAN
    # log does not say which strategy produced its results: compare anyway)
    events = trace.events
    matches = None
    same_run = (strategy == src.logged_strategy and (src.logged_seed is None or seed == src.logged_seed)) or \
        (src.kind == "can-log" and src.logged_strategy is None)
    if src.logged_events is not None and same_run:
        limit = math.inf if src.logged_last_step is None else src.logged_last_step
        matches = events_match([_event_key(e) for e in events if e.step <= limit],
                               [e for e in src.logged_events if e[0] <= limit])

    readings = node.sensor_frames
    logged_corr = None if src.logged_events is None else sum(1 for e in src.logged_events if e[1] == "correction")
    logged_conf = None if src.logged_events is None else next(
        (e for e in src.logged_events if e[1] == "confirmed"), None)
    # a closed-loop run's torques came from its own law acting on its own identifier: another strategy
    # would have commanded other torques, so the plant's readings (replayed as logged) are not what it would have met
    closed_loop = scenario.control.law != "demand"
    counterfactual = closed_loop and strategy != src.logged_strategy
    extra = {"mode": "replay", "source": src.kind, "wall_s": wall, "control": scenario.control.law,
             "counterfactual": counterfactual,
             "sim_s": (node.last_step + 1) * period if node.last_step >= 0 else 0.0,
             "samples_per_s": readings / wall if wall > 0 else None, "sensor_readings": readings,
             "rejected_frames": dict(node.rejected), "messages_read": src.messages_read,
             "matches_log": matches, "log_complete": src.complete, "damage": src.damage or None,
             "logged": {"strategy": src.logged_strategy, "seed": src.logged_seed, "corrections": logged_corr,
                        "t_identified_s": None if logged_conf is None else logged_conf[0] * period,
                        "params": None if logged_conf is None else list(logged_conf[3])}}
    return clean(trace.summary(strategy=strategy, seed=seed, bus="replay", mcap_path=src.path, extra=extra))


def replay_log(path, scenario_file=None, strategy: str | None = None, seed: int | None = None) -> dict:
    """``hil replay`` as a call: read the log at ``path`` (an MCAP log, or a CAN log with its
    ``scenario_file``) and re-identify it (``replay``)."""
    return replay(load_source(path, scenario_file), strategy, seed)


def damage_warning(src: ReplaySource) -> str | None:
    """One line for stderr saying how much of a damaged log was recovered (None for a whole log)."""
    if src.complete:
        return None
    period = src.scenario.run.exchange_period_s
    what = (f"is damaged ({src.damage})" if src.damage else
            f"holds a run that did not finish ({src.ended_early or 'no summary'}; the log was closed properly)")
    return (f"warning: {src.path} {what}; recovered {src.messages_read} messages, "
            f"{len(src.frames)} sensor frames (about {len(src.frames) * period:.3f} s of the run); "
            + ("replaying what survived the damage" if src.damage else "replaying what was recorded"))

