"""The HIL frames (``hil/hil.dbc``), encoded and decoded with layouts compiled from the DBC.

The DBC is the one source of the frame layouts.  At load, each frame whose signals are all
byte-aligned little-endian integers or IEEE floats without scaling (every frame of ``hil.dbc``
today) is compiled to a ``struct`` format (``FrameLayout``): a few microseconds a frame less than
cantools' general encoder, on the loop's path twice a period each way.  A frame the compiler
cannot express is encoded and decoded by cantools; the tests check both give the same bytes and
values.

``FrameCodec`` maps ``identifier.messages`` dataclasses to ``can.Message`` and back.  Every received
frame goes through ``FrameCodec.classify``: it either yields a decoded ``Frame`` or a rejection
reason (unknown id, wrong length, error/remote frame, ``forged`` or ``replayed`` when the codec
authenticates (``hil/bus/secoc.py``), undecodable, non-finite or out-of-range signal).  Rejected frames
are counted by reason (``RejectCounter``) and never reach the identifier.  Every frame ends with the
authentication trailer (``AuthFreshness``, ``AuthMac``); a codec without an ``Authenticator`` sends it
zeroed and does not read it.

Frame schedule per exchange period: DriverDemand then PlantSensor (plant -> TCU), then TorqueCommand, TcuSample (0..n,
one per sample the strategy took), TcuResult (0..n, only on an identification event, each followed by its
TcuInterval when the strategy says how sure it is), TcuEstimate (every ``ESTIMATE_TRACE_STEPS``-th period
while the TCU estimates the current rail's peak, in closed loop; optional) and TcuStatus
(TCU -> plant, in this order), heartbeats both ways every ``heartbeat_period_s`` of wall time.
"""
from __future__ import annotations

import math
import struct
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import can
import cantools

from identifier.messages import (ESTIMATE_TRACE_STEPS, DriverDemand, IdentificationEvent, ObserverSample,
                                 SensorReading, TcuStatus, TorqueCommand)

DBC_NAME = "hil.dbc"
DBC_PATH = Path(__file__).parent.parent / DBC_NAME

# frame ids (also in the DBC; checked against it at load)
SENSOR_ID, COMMAND_ID, STATUS_ID, RESULT_ID, INTERVAL_ID, SAMPLE_ID = 0x100, 0x110, 0x120, 0x130, 0x131, 0x140
ESTIMATE_ID = 0x132
DEMAND_ID = 0x108
PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID = 0x701, 0x702
#: the TCU's scenario digest, sent before each heartbeat until the first reading (``FrameCodec.tcu_scenario``)
TCU_SCENARIO_ID = 0x703
#: frames sent by the wall clock, not by the exchange (heartbeats, the TCU's scenario announcement before its first
#: reading): how many a run holds depends on timing, so comparisons of runs' frame streams leave them out
WALL_CLOCK_IDS = frozenset({PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID, TCU_SCENARIO_ID})
PLANT_IDS = frozenset({SENSOR_ID, DEMAND_ID, PLANT_HEARTBEAT_ID})
TCU_IDS = frozenset({COMMAND_ID, STATUS_ID, RESULT_ID, INTERVAL_ID, ESTIMATE_ID, SAMPLE_ID, TCU_HEARTBEAT_ID,
                     TCU_SCENARIO_ID})

# heartbeat states
STATE_STARTING, STATE_RUNNING, STATE_FINISHED, STATE_FAULT = 0, 1, 2, 3
STATE_NAMES = {STATE_STARTING: "starting", STATE_RUNNING: "running", STATE_FINISHED: "finished",
               STATE_FAULT: "fault"}

MAX_PARAMS = 5
KINDS = ("correction", "confirmed", "unconfirmed")
#: the coverage of the intervals a TCU sends with each result
INTERVAL_LEVEL_PERCENT = 90
#: signals allowed to be non-finite (J_EF is inf before the 2nd correction and NaN on confirmation)
NON_FINITE_OK = frozenset({"JEf"})
#: the authentication trailer's signals (every frame's last; hil/bus/secoc.py)
AUTH_SIGNALS = ("AuthFreshness", "AuthMac")
_INF = math.inf


def load_dbc() -> cantools.database.can.Database:
    return cantools.database.load_file(str(DBC_PATH), database_format="dbc")


@dataclass(frozen=True)
class Heartbeat:
    counter: int
    state: int
    step: int


@dataclass(frozen=True)
class IntervalReport:
    """The intervals that go with the result of (step, correction, kind)."""
    step: int
    correction: int
    kind: str
    level_percent: int
    peak_mu_ci: tuple[float, float]
    peak_creep_ci: tuple[float, float]
    peak_open: bool = False      # the upper ends are the TCU's working range, not the data's (IdentificationEvent)
    samples_from_s: float = math.nan     # the span of the samples the result rests on (IdentificationEvent; NaN: not
    samples_to_s: float = math.nan       # stated)


@dataclass(frozen=True)
class SampleReport:
    """One (creep, mu^) sample the TCU's strategy took, and when the TCU dates the slip's start."""
    step: int
    index: int
    detected_step: int
    creep_speed_kmh: float
    mu_hat: float


@dataclass(frozen=True)
class EstimateReport:
    """The TCU's estimate of the current rail's peak at ``step`` as a TcuEstimate frame carries it: the fields
    of ``identifier.peak_estimate.PeakEstimate`` but its sample count (``t_s`` is ``step`` periods)."""
    step: int
    t_s: float
    peak_creep_kmh: float
    peak_creep_ci: tuple[float, float]
    peak_mu: float
    peak_mu_ci: tuple[float, float]
    since_step: int


class Frame(NamedTuple):
    """A received frame that passed validation: its DBC name and the decoded object (``demand``: the
    driver's demand a mapped sensor frame carries too, ``hil.bus.mapping``).  A named tuple: several are
    made each period, and a tuple is cheaper to build than a frozen dataclass."""
    name: str
    value: object          # SensorReading | DriverDemand | TorqueCommand | (TcuStatus, ObserverSample|None) | IdentificationEvent | IntervalReport | SampleReport | Heartbeat
    demand: DriverDemand | None = None


class RejectCounter(Counter):
    """Rejected frames by reason (``unknown_id``, ``bad_length``, ``non_finite:MotorSpeed`` ...)."""

    @property
    def total(self) -> int:
        return sum(self.values())


#: (is_float, signed, bits) -> struct code
_STRUCT_CODES = {(True, True, 32): "f", (True, True, 64): "d",
                 (False, False, 8): "B", (False, False, 16): "H", (False, False, 32): "I", (False, False, 64): "Q",
                 (False, True, 8): "b", (False, True, 16): "h", (False, True, 32): "i", (False, True, 64): "q"}


class FrameLayout:
    """One frame's payload signals (the authentication trailer left out: it is packed as zeros and
    filled by ``hil.bus.secoc``) as a little-endian ``struct`` format compiled from the DBC message.

    ``compile(message)`` returns None when a signal is not byte-aligned little-endian, not 8/16/32/64
    bits, scaled, offset or multiplexed: cantools then does that frame.  ``pack(values)`` takes a
    dict by signal name (as cantools' ``encode``); ``unpack(data)`` gives the values in ``names`` order
    (as cantools' ``decode`` with ``scaling=True, decode_choices=False``)."""

    def __init__(self, names: tuple[str, ...], fmt: str):
        self.names = names
        self.struct = struct.Struct(fmt)

    @classmethod
    def compile(cls, message) -> "FrameLayout | None":
        if message.is_multiplexed():
            return None
        fmt, at, names = "<", 0, []
        for sig in sorted((s for s in message.signals if s.name not in AUTH_SIGNALS), key=lambda s: s.start):
            code = _STRUCT_CODES.get((bool(sig.is_float), bool(sig.is_signed) or bool(sig.is_float), sig.length))
            if (code is None or sig.byte_order != "little_endian" or sig.start % 8 or sig.start < at
                    or sig.scale != 1 or sig.offset != 0):
                return None
            fmt += "x" * ((sig.start - at) // 8) + code
            at = sig.start + sig.length
            names.append(sig.name)
        if at > message.length * 8 or at % 8:
            return None
        return cls(tuple(names), fmt + "x" * (message.length - at // 8))

    def pack(self, values: dict) -> bytes:
        return self.struct.pack(*[values[n] for n in self.names])

    def unpack(self, data: bytes) -> tuple:
        return self.struct.unpack(data)


class FrameCodec:
    """Encode/decode between frames and ``identifier.messages`` dataclasses, through the DBC.
    ``auth``: the key (16 bytes) this node authenticates with (``hil/bus/secoc.py``); None: it fills the
    trailer with zeros and does not check it."""

    def __init__(self, period_s: float, db=None, auth=None):
        self.db = db or load_dbc()
        self.period_s = period_s
        self._by_id = {m.frame_id: m for m in self.db.messages}
        expected = {SENSOR_ID: "PlantSensor", DEMAND_ID: "DriverDemand", COMMAND_ID: "TorqueCommand", STATUS_ID: "TcuStatus",
                    RESULT_ID: "TcuResult", INTERVAL_ID: "TcuInterval", ESTIMATE_ID: "TcuEstimate", SAMPLE_ID: "TcuSample",
                    PLANT_HEARTBEAT_ID: "PlantHeartbeat", TCU_HEARTBEAT_ID: "TcuHeartbeat", TCU_SCENARIO_ID: "TcuScenario"}
        for fid, name in expected.items():
            if fid not in self._by_id or self._by_id[fid].name != name:
                raise ValueError(f"{DBC_NAME}: frame 0x{fid:X} must be {name}")
        self._limits = {fid: [(s.name, s.is_float, s.minimum, s.maximum) for s in m.signals
                              if s.name not in AUTH_SIGNALS]
                        for fid, m in self._by_id.items()}
        #: compiled layouts (None: cantools does that frame); the limits in each layout's order
        self.layouts = {fid: FrameLayout.compile(m) for fid, m in self._by_id.items()}
        for fid, layout in self.layouts.items():
            if layout is not None:
                by_name = {x[0]: x for x in self._limits[fid]}
                self._limits[fid] = [by_name[n] for n in layout.names]
        #: per frame id, what ``classify`` reads for every frame: (name, length, layout, limits in the layout's
        #: order with no bound as an infinite one)
        inf = math.inf
        self._decoders = {fid: (m.name, m.length, self.layouts[fid],
                                tuple((name, is_float, -inf if lo is None else lo, inf if hi is None else hi)
                                      for name, is_float, lo, hi in self._limits[fid]))
                          for fid, m in self._by_id.items()}
        #: per frame id with a compiled layout, what ``_classify`` runs (``_compile_decoders``)
        self._fast = self._compile_decoders()
        #: where each frame's authentication trailer starts (bytes)
        self.trailer_offsets = {fid: m.get_signal_by_name(AUTH_SIGNALS[0]).start // 8
                                for fid, m in self._by_id.items()}
        self.auth = None
        if auth is not None:
            from .secoc import Authenticator
            self.auth = Authenticator(auth, self.trailer_offsets)

    def _compile_decoders(self) -> dict:
        """Per frame id with a compiled layout: (name, length, unpack, checks, build).  ``unpack`` gives the
        values in the layout's order, ``checks`` the (position, signal, is_float, lo, hi) of each bounded
        signal, ``build`` the decoded object from the values by position: ``_to_object``'s objects
        without a dict of the values per frame (the dict path stays for frames cantools decodes)."""
        out = {}
        for fid, (name, length, layout, limits) in self._decoders.items():
            if layout is None:
                continue
            at = {n: i for i, n in enumerate(layout.names)}
            checks = tuple((at[signal], signal, is_float, lo, hi) for signal, is_float, lo, hi in limits)
            build = self._builder(fid, at)
            if build is not None:
                out[fid] = (name, length, layout.struct.unpack, checks, build)
        return out

    def _builder(self, fid: int, at: dict):
        """``_to_object`` for frame ``fid`` as a function of the unpacked values (``at``: signal -> position);
        None for a frame it does not know."""
        try:
            if fid == SENSOR_ID:
                i, m, t = at["SensorStep"], at["MotorSpeed"], at["TrainSpeed"]
                return lambda v: SensorReading(int(v[i]), float(v[m]), float(v[t]))
            if fid == COMMAND_ID:
                i, q = at["CommandStep"], at["TorqueCmd"]
                return lambda v: TorqueCommand(int(v[i]), float(v[q]))
            if fid == DEMAND_ID:
                i, q = at["DemandStep"], at["DemandTorque"]
                return lambda v: DriverDemand(int(v[i]), float(v[q]))
            if fid == STATUS_ID:
                i, g, c, ok = at["StatusStep"], at["Stage"], at["Correction"], at["ObserverValid"]
                cr, mu, lt, period = at["CreepSpeed"], at["MuHat"], at["LoadTorque"], self.period_s

                def status(v):
                    step = int(v[i])
                    obs = ObserverSample(step, step * period, float(v[cr]), float(v[mu]), float(v[lt])) if v[ok] \
                        else None
                    return TcuStatus(step, int(v[g]), int(v[c])), obs
                return status
            if fid == SAMPLE_ID:
                i, x, d, cr, mu = (at["SampleStep"], at["SampleIndex"], at["DetectedStep"], at["SampleCreep"],
                                   at["SampleMu"])
                return lambda v: SampleReport(int(v[i]), int(v[x]), int(v[d]), float(v[cr]), float(v[mu]))
            if fid == PLANT_HEARTBEAT_ID:
                c, st, i = at["PlantCounter"], at["PlantState"], at["PlantStep"]
                return lambda v: Heartbeat(int(v[c]), int(v[st]), int(v[i]))
            if fid == TCU_HEARTBEAT_ID:
                c, st, i = at["TcuCounter"], at["TcuState"], at["TcuStep"]
                return lambda v: Heartbeat(int(v[c]), int(v[st]), int(v[i]))
        except KeyError:          # a DBC whose frame lacks a signal: the dict path says so when it comes
            return None
        names = tuple(at)         # the rarer frames (results, intervals, the scenario word): the dict path
        return lambda v: self._to_object(fid, dict(zip(names, v)))

    # -- encoding ------------------------------------------------------------------------------
    def _msg(self, fid: int, values: dict) -> can.Message:
        layout = self.layouts[fid]
        try:
            data = layout.pack(values)
        except (AttributeError, struct.error, OverflowError):   # no layout, or a value the format cannot hold:
            data = self._by_id[fid].encode({**values, "AuthFreshness": 0, "AuthMac": 0}, scaling=True, padding=False,
                                           strict=False)      # cantools' rounding (1e39 -> inf)
        if self.auth is not None:
            data = self.auth.protect(fid, bytes(data))
        return can.Message(arbitration_id=fid, data=data, is_extended_id=False, is_fd=True, bitrate_switch=True)

    def sensor(self, r: SensorReading) -> can.Message:
        return self._msg(SENSOR_ID, {"SensorStep": r.step, "MotorSpeed": r.motor_speed_rad_s,
                                     "TrainSpeed": r.train_speed_ms})

    def demand(self, d: DriverDemand) -> can.Message:
        return self._msg(DEMAND_ID, {"DemandStep": d.step, "DemandTorque": d.torque_nm})

    def command(self, c: TorqueCommand) -> can.Message:
        return self._msg(COMMAND_ID, {"CommandStep": c.step, "TorqueCmd": c.torque_nm})

    def status(self, st: TcuStatus, obs: ObserverSample | None) -> can.Message:
        valid = obs is not None
        return self._msg(STATUS_ID, {"StatusStep": st.step, "Stage": st.stage, "ObserverValid": int(valid),
                                     "Correction": st.correction,
                                     "MuHat": obs.mu_hat if valid else 0.0,
                                     "CreepSpeed": obs.creep_speed_kmh if valid else 0.0,
                                     "LoadTorque": obs.load_torque_nm if valid else 0.0})

    def result(self, e: IdentificationEvent) -> can.Message:
        if len(e.params) > MAX_PARAMS:
            raise ValueError(f"TcuResult carries at most {MAX_PARAMS} curve parameters, got {len(e.params)}")
        values = {"ResultStep": e.step, "ResultCorrection": e.correction, "ResultSamples": min(e.samples, 65535),
                  "ResultKind": KINDS.index(e.kind), "ParamCount": len(e.params), "JEf": e.j_ef}
        for i in range(MAX_PARAMS):
            values[f"Param{i}"] = e.params[i] if i < len(e.params) else 0.0
        return self._msg(RESULT_ID, values)

    def interval(self, e: IdentificationEvent) -> can.Message | None:
        """The TcuInterval frame of an event, or None when it carries no (finite) interval."""
        values = (*e.peak_mu_ci, *e.peak_creep_ci)
        if not all(math.isfinite(x) for x in values):
            return None
        signals = {"PeakMuLo": values[0], "PeakMuHi": values[1], "PeakCreepLo": values[2], "PeakCreepHi": values[3]}
        limits = {name: (lo, hi) for name, _, lo, hi in self._limits[INTERVAL_ID]}
        if not all(limits[k][0] <= v <= limits[k][1] for k, v in signals.items()):
            return None            # beyond the DBC's ranges: sent as no interval rather than as a frame to reject
        return self._msg(INTERVAL_ID, {"IntervalStep": e.step, "IntervalCorrection": e.correction,
                                       "IntervalKind": KINDS.index(e.kind), "IntervalLevel": INTERVAL_LEVEL_PERCENT,
                                       **signals, "IntervalOpen": int(bool(e.peak_open)), **self._span(e)})

    def _span(self, e: IdentificationEvent) -> dict:
        """SamplesStated, SamplesFromStep, SamplesToStep of an event (its samples' span, as steps; 0 when not stated)."""
        a, b = getattr(e, "samples_from_s", math.nan), getattr(e, "samples_to_s", math.nan)
        if not (math.isfinite(a) and math.isfinite(b) and 0.0 <= a <= b):
            return {"SamplesStated": 0, "SamplesFromStep": 0, "SamplesToStep": 0}
        return {"SamplesStated": 1, "SamplesFromStep": min(round(a / self.period_s), 0xFFFFFFFF),
                "SamplesToStep": min(round(b / self.period_s), 0xFFFFFFFF)}

    def estimate(self, e) -> can.Message | None:
        """The TcuEstimate frame of a peak estimate (``PeakEstimate`` or ``EstimateReport``), or None when a
        value is not finite or lies beyond the DBC's ranges (sent as no estimate rather than as a frame to reject)."""
        signals = {"EstPeakCreep": e.peak_creep_kmh, "EstPeakCreepLo": e.peak_creep_ci[0],
                   "EstPeakCreepHi": e.peak_creep_ci[1], "EstPeakMu": e.peak_mu, "EstPeakMuLo": e.peak_mu_ci[0],
                   "EstPeakMuHi": e.peak_mu_ci[1]}
        limits = {name: (lo, hi) for name, _, lo, hi in self._limits[ESTIMATE_ID]}
        if not all(math.isfinite(v) and limits[k][0] <= v <= limits[k][1] for k, v in signals.items()):
            return None
        return self._msg(ESTIMATE_ID, {"EstimateStep": e.step, "SinceStep": max(int(e.since_step), 0), **signals})

    def sample(self, r: SampleReport) -> can.Message:
        return self._msg(SAMPLE_ID, {"SampleStep": r.step, "SampleIndex": min(r.index, 65535),
                                     "DetectedStep": r.detected_step, "SampleCreep": r.creep_speed_kmh,
                                     "SampleMu": r.mu_hat})

    def plant_heartbeat(self, counter: int, state: int, step: int) -> can.Message:
        return self._msg(PLANT_HEARTBEAT_ID, {"PlantCounter": counter & 0xFFFF, "PlantState": state,
                                              "PlantStep": max(step, 0)})

    def tcu_heartbeat(self, counter: int, state: int, step: int) -> can.Message:
        return self._msg(TCU_HEARTBEAT_ID, {"TcuCounter": counter & 0xFFFF, "TcuState": state,
                                            "TcuStep": max(step, 0)})

    def tcu_scenario(self, digest_hex: str) -> can.Message:
        """The TcuScenario frame: ``scenario_digest_word`` of the scenario's SHA-256 (hex)."""
        return self._msg(TCU_SCENARIO_ID, {"ScenarioDigest": scenario_digest_word(digest_hex)})

    # -- decoding ------------------------------------------------------------------------------
    def upgrade(self, msg: can.Message) -> can.Message:
        """A frame recorded before the DBC had the authentication trailer (its length then ended where
        the trailer now starts) as today's frame: the same bytes, a zero trailer.  Any other frame is
        returned as it is.  For replaying old logs (``hil replay``, ``hil gap``); never on a live bus."""
        at = self.trailer_offsets.get(msg.arbitration_id)
        m = self._by_id.get(msg.arbitration_id)
        if at is None or msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or len(msg.data) != at \
                or m.length == at:
            return msg
        data = bytes(msg.data) + bytes(m.length - at)
        return can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id, data=data,
                           is_extended_id=False, is_fd=True, bitrate_switch=msg.bitrate_switch, channel=msg.channel)

    def classify(self, msg: can.Message) -> tuple[Frame | None, str]:
        """(Frame, "ok") for a valid frame, else (None, reason).  Never raises."""
        try:
            return self._classify(msg)
        except Exception as e:  # noqa: BLE001 - a frame must never crash a node
            return None, f"undecodable:{type(e).__name__}"

    def _classify(self, msg: can.Message) -> tuple[Frame | None, str]:
        if msg.is_error_frame:
            return None, "error_frame"
        if msg.is_remote_frame:
            return None, "remote_frame"
        fid = msg.arbitration_id
        fast = None if msg.is_extended_id else self._fast.get(fid)
        if fast is not None:          # a compiled layout (every frame of hil.dbc): no dict of values
            name, length, unpack, checks, build = fast
            data = bytes(msg.data)
            if len(data) != length:
                return None, "bad_length"
            if self.auth is not None:
                verdict = self.auth.verify(fid, data)
                if verdict != "ok":
                    return None, verdict
            v = unpack(data)
            for i, signal, is_float, lo, hi in checks:
                x = v[i]
                if lo <= x <= hi and (not is_float or -_INF < x < _INF):     # finite and in range (NaN fails)
                    continue
                if is_float and not math.isfinite(x):
                    if signal in NON_FINITE_OK:
                        continue
                    return None, f"non_finite:{signal}"
                return None, f"out_of_range:{signal}"
            return Frame(name, build(v)), "ok"
        entry = None if msg.is_extended_id else self._decoders.get(fid)
        if entry is None:
            return None, "unknown_id"
        name, length, layout, limits = entry
        data = bytes(msg.data)
        if len(data) != length:
            return None, "bad_length"
        if self.auth is not None:
            verdict = self.auth.verify(fid, data)
            if verdict != "ok":
                return None, verdict
        if layout is not None:
            values = dict(zip(layout.names, layout.unpack(data)))
        else:
            values = self._by_id[fid].decode(data, decode_choices=False, scaling=True)
        for signal, is_float, lo, hi in limits:
            x = values[signal]
            if is_float and not math.isfinite(x):
                if signal in NON_FINITE_OK:
                    continue
                return None, f"non_finite:{signal}"
            if not lo <= x <= hi:
                return None, f"out_of_range:{signal}"
        return Frame(name, self._to_object(fid, values)), "ok"

    def _to_object(self, fid: int, v: dict):
        if fid == SENSOR_ID:
            return SensorReading(int(v["SensorStep"]), float(v["MotorSpeed"]), float(v["TrainSpeed"]))
        if fid == COMMAND_ID:
            return TorqueCommand(int(v["CommandStep"]), float(v["TorqueCmd"]))
        if fid == DEMAND_ID:
            return DriverDemand(int(v["DemandStep"]), float(v["DemandTorque"]))
        if fid == STATUS_ID:
            step = int(v["StatusStep"])
            status = TcuStatus(step, int(v["Stage"]), int(v["Correction"]))
            obs = ObserverSample(step, step * self.period_s, float(v["CreepSpeed"]), float(v["MuHat"]),
                                 float(v["LoadTorque"])) if v["ObserverValid"] else None
            return status, obs
        if fid == RESULT_ID:
            step = int(v["ResultStep"])
            n = int(v["ParamCount"])
            return IdentificationEvent(step, step * self.period_s, KINDS[int(v["ResultKind"])],
                                       int(v["ResultCorrection"]),
                                       tuple(float(v[f"Param{i}"]) for i in range(n)), float(v["JEf"]),
                                       int(v["ResultSamples"]))
        if fid == INTERVAL_ID:
            return IntervalReport(int(v["IntervalStep"]), int(v["IntervalCorrection"]), KINDS[int(v["IntervalKind"])],
                                  int(v["IntervalLevel"]), (float(v["PeakMuLo"]), float(v["PeakMuHi"])),
                                  (float(v["PeakCreepLo"]), float(v["PeakCreepHi"])), bool(v["IntervalOpen"]),
                                  *((int(v["SamplesFromStep"]) * self.period_s, int(v["SamplesToStep"]) * self.period_s)
                                    if v.get("SamplesStated") else (math.nan, math.nan)))
        if fid == ESTIMATE_ID:
            step = int(v["EstimateStep"])
            return EstimateReport(step, step * self.period_s, float(v["EstPeakCreep"]),
                                  (float(v["EstPeakCreepLo"]), float(v["EstPeakCreepHi"])), float(v["EstPeakMu"]),
                                  (float(v["EstPeakMuLo"]), float(v["EstPeakMuHi"])), int(v["SinceStep"]))
        if fid == SAMPLE_ID:
            return SampleReport(int(v["SampleStep"]), int(v["SampleIndex"]), int(v["DetectedStep"]),
                                float(v["SampleCreep"]), float(v["SampleMu"]))
        if fid == PLANT_HEARTBEAT_ID:
            return Heartbeat(int(v["PlantCounter"]), int(v["PlantState"]), int(v["PlantStep"]))
        if fid == TCU_HEARTBEAT_ID:
            return Heartbeat(int(v["TcuCounter"]), int(v["TcuState"]), int(v["TcuStep"]))
        if fid == TCU_SCENARIO_ID:
            return int(v["ScenarioDigest"])
        raise AssertionError(fid)


def scenario_digest_word(digest_hex: str) -> int:
    """What a TcuScenario frame carries of a SHA-256 digest (hex): its first 8 bytes, big-endian."""
    return int(digest_hex[:16], 16)


# -- bus load ---------------------------------------------------------------------------------
def fd_frame_time_s(data_len: int, bitrate: int, data_bitrate: int, brs: bool = True) -> float:
    """Worst-case duration (s) of one CAN FD base-format (11-bit id) data frame with ``data_len`` bytes.

    Arbitration phase at ``bitrate``: SOF, 11-bit id, RRS, IDE, FDF, res, BRS (17 bits) plus the
    closing CRC delimiter, ACK slot, ACK delimiter, 7-bit EOF and 3-bit intermission (13 bits).
    Data phase at ``data_bitrate`` (``bitrate`` without BRS): ESI, 4-bit DLC, data, 4-bit stuff
    count with parity, CRC-17 (<= 16 bytes) or CRC-21, and a fixed stuff bit every 4 bits of the
    stuff-count + CRC field.  Dynamic stuffing is taken at its worst case, one stuff bit per 4 bits
    after the first (as in the classic ``(34 + 8n - 1) / 4`` bound), on the arbitration header and
    on ESI + DLC + data.
    """
    arb = 17 + (17 - 1) // 4
    crc = 17 if data_len <= 16 else 21
    dyn = 1 + 4 + 8 * data_len
    data_bits = dyn + (dyn - 1) // 4 + 4 + crc + math.ceil((crc + 4) / 4)
    tail = 13
    return (arb + tail) / bitrate + data_bits / (data_bitrate if brs else bitrate)


def bus_load(db, period_s: float, heartbeat_period_s: float, bitrate: int, data_bitrate: int) -> dict:
    """Worst-case bus load of the HIL schedule: per exchange period one sensor, status and command
    frame, and a peak estimate every ``ESTIMATE_TRACE_STEPS`` periods (closed loop); heartbeats from both sides
    every ``heartbeat_period_s``; the peak adds a sample frame and a result frame in the same period (samples
    flow only while identifying; results once a window).
    """
    lengths = {m.frame_id: m.length for m in db.messages}
    per_period = sum(fd_frame_time_s(lengths[i], bitrate, data_bitrate) for i in (SENSOR_ID, STATUS_ID, COMMAND_ID))
    heartbeats = sum(fd_frame_time_s(lengths[i], bitrate, data_bitrate)
                     for i in (PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID)) / heartbeat_period_s
    if ESTIMATE_ID in lengths:
        per_period += fd_frame_time_s(lengths[ESTIMATE_ID], bitrate, data_bitrate) / ESTIMATE_TRACE_STEPS
    steady = per_period / period_s + heartbeats
    peak = steady + sum(fd_frame_time_s(lengths[i], bitrate, data_bitrate) for i in (RESULT_ID, SAMPLE_ID)) / period_s
    return {"bitrate": bitrate, "data_bitrate": data_bitrate, "period_s": period_s,
            "heartbeat_period_s": heartbeat_period_s, "load_percent": 100.0 * steady,
            "peak_load_percent": 100.0 * peak}


def format_bus_load(load: dict) -> str:
    """Two lines for a terminal: the load, then the settings it was computed at (indented)."""
    return (f"bus load {load['load_percent']:.1f} % (peak {load['peak_load_percent']:.1f} % with a sample and a result "
            f"frame)\n  at {load['bitrate'] / 1e3:g} kbit/s arbitration, {load['data_bitrate'] / 1e6:g} Mbit/s data, "
            f"{load['period_s'] * 1e3:g} ms exchange period")
