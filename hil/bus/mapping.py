"""A TCU's own DBC: the plant's quantities mapped onto its messages and signals (``[bus] dbc`` and
``[bus.mapping]``), and the codec that speaks it (``MappedCodec``).

A TCU of another make speaks its supplier's DBC: classical CAN (8-byte frames), scaled integer
signals, no step counters and no authentication trailer.  The mapping names, for each quantity the
plant sends and each it receives, the message and signal that carries it::

    motor_speed_rad_s = "Sensors.MotorSpeed"       # plant -> TCU
    train_speed_ms    = "Sensors.TrainSpeed"       # plant -> TCU
    demand_torque_nm  = "Notch.DemandTorque"       # plant -> TCU (the driver's demand)
    torque_command_nm = "TcuCmd.TorqueRequest"     # TCU -> plant

Scale, offset, length and signedness come from their DBC; cantools encodes and decodes (the HIL's own
frames keep their compiled layouts, ``hil.bus.frames``).  A value beyond what the signal can carry is
sent saturated at its end, as a sensor saturates.  The other signals of a message the plant sends
are sent as their DBC initial value (0 when none, clipped into the signal's range).

Per exchange period the plant sends each of its mapped messages once, the messages that carry only
the demand first and the one that carries the motor speed last (the *trigger*: its arrival is a new
reading for the TCU).  A message whose DBC cycle time (``GenMsgCycleTime``) differs from the
exchange period is refused.  Without step counters the steps are counted: the TCU side numbers the
trigger frames it receives, the plant side takes the first command frame after its frames of a period
as that period's answer (``hil.plant_node``).

A TCU sends more than its command: ``tcu_frames = ["TcuStatus", "TcuDiag"]`` in ``[bus.mapping]`` names
its other messages (status, diagnostics), any number, each with its own id.  The plant accepts them
(logged with status ``ok``: checks name their signals) and acts on none.  Every signal of every mapped
message received is range-checked against its DBC minimum and maximum on receipt and counted per
signal (``MappedCodec.out_of_range``; the run summary's ``out_of_range_signals``, "Message.Signal" ->
count, every signal of a message received listed, 0 included, so a ``limit`` can require 0); a mapped
quantity's signal out of range rejects its frame (``out_of_range:Signal``), another signal's does not.
A frame whose id the mapping does not name and that is no HIL frame is counted by id
(``unmapped_id:0x123``, passed, not acted on; the summary's ``unmapped_ids``).

The HIL's own frames (heartbeats both ways and the built-in TCU's identification frames TcuStatus,
TcuResult, TcuInterval, TcuEstimate, TcuSample: CAN FD, ``hil/hil.dbc``) still travel beside the mapped ones; a
TCU of another make sends none and ignores them.  Their ids are therefore reserved: a mapped message
with one of them is refused.

Every problem with a mapping is one ``ConfigError`` line naming the scenario file and the key.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import can

from identifier.messages import DriverDemand, SensorReading, TorqueCommand

from ..errors import ConfigError
from .frames import (COMMAND_ID, DBC_PATH, DEMAND_ID, ESTIMATE_ID, INTERVAL_ID, PLANT_HEARTBEAT_ID, RESULT_ID,
                     SAMPLE_ID, SENSOR_ID, STATUS_ID, TCU_HEARTBEAT_ID, Frame, FrameCodec)

#: the quantities the plant sends, and the one it receives
SENT = ("motor_speed_rad_s", "train_speed_ms", "demand_torque_nm")
RECEIVED = ("torque_command_nm",)
QUANTITIES = SENT + RECEIVED
#: the key of [bus.mapping] that names the TCU's other messages (status, diagnostics)
TCU_FRAMES = "tcu_frames"
#: the HIL frames that still travel on a mapped bus (heartbeats, the built-in TCU's identification frames)
RESERVED_IDS = {PLANT_HEARTBEAT_ID: "PlantHeartbeat", TCU_HEARTBEAT_ID: "TcuHeartbeat", STATUS_ID: "TcuStatus",
                RESULT_ID: "TcuResult", INTERVAL_ID: "TcuInterval", ESTIMATE_ID: "TcuEstimate", SAMPLE_ID: "TcuSample"}


@dataclass(frozen=True)
class Need:
    """The range a quantity's signal must carry in a scenario (``needed_ranges``)."""
    lo: float
    hi: float
    why: str


def needed_ranges(scenario) -> dict[str, Need]:
    """What each mapped signal must carry: the speeds from 0 to twice their start (a slipping wheel
    spins up), the torques from 0 to 1.2 times the largest demand (a law's excitation rides on top)."""
    v = scenario.vehicle
    v0 = scenario.run.initial_train_speed_ms
    motor0 = v0 * v.gear_ratio / v.wheel_radius_m
    demand = scenario.control.demand
    mus = demand.demand_mu if demand is not None else ()
    top = max([scenario.identifier_settings().torque_demand_nm] + [m * v.torque_per_mu_nm for m in mus])
    return {"motor_speed_rad_s": Need(0.0, 2 * motor0, "0 to twice the starting motor speed"),
            "train_speed_ms": Need(0.0, 2 * v0, "0 to twice the starting train speed"),
            "demand_torque_nm": Need(0.0, 1.2 * top, "0 to 1.2 x the largest demand"),
            "torque_command_nm": Need(0.0, 1.2 * top, "0 to 1.2 x the largest demand")}


def signal_span(sig) -> tuple[float, float]:
    """The physical values a signal can carry: its raw integer range scaled, within its DBC minimum and
    maximum when given."""
    if sig.is_float:
        lo, hi = -math.inf, math.inf
    elif sig.is_signed:
        lo, hi = -(2 ** (sig.length - 1)), 2 ** (sig.length - 1) - 1
    else:
        lo, hi = 0, 2 ** sig.length - 1
    a, b = sorted((lo * sig.scale + sig.offset, hi * sig.scale + sig.offset))
    if sig.minimum is not None:
        a = max(a, sig.minimum)
    if sig.maximum is not None:
        b = min(b, sig.maximum)
    return a, b


#: the database attributes that name a bus's bit rates: the arbitration rate (Vector's ``Baudrate``), and the
#: CAN FD data-phase rate (``BaudrateCANFD`` as CANdb++ writes it; the other spellings seen in the wild)
BITRATE_ATTRIBUTES = ("Baudrate",)
DATA_BITRATE_ATTRIBUTES = ("BaudrateCANFD", "BaudRateCANFD", "DataBaudrate", "FDBaudrate", "BaudrateFD")


def dbc_bitrates(db) -> tuple[int | None, int | None]:
    """(arbitration bit rate, CAN FD data bit rate) in bit/s that a DBC's database attributes name, each None
    where it names none (or a value that is no positive integer)."""
    attrs = getattr(getattr(db, "dbc", None), "attributes", None) or {}

    def rate(names):
        for name in names:
            if name in attrs:
                try:
                    value = int(attrs[name].value)
                except (TypeError, ValueError):  # a non-numeric attribute: not a rate, the next name is tried
                    continue
                if value > 0:
                    return value
        return None

    return rate(BITRATE_ATTRIBUTES), rate(DATA_BITRATE_ATTRIBUTES)


@dataclass(frozen=True)
class Mapping:
    """A loaded mapping: their database, and per quantity (message, signal)."""
    dbc_path: str
    db: object
    where: dict          # quantity -> (message, signal name)
    tcu_frames: tuple = ()   # the TCU's other messages (``tcu_frames``), in the mapping's order

    @property
    def bitrates(self) -> tuple[int | None, int | None]:
        """The bus's bit rates as their DBC names them (``dbc_bitrates``): they set the bus-load figures."""
        return dbc_bitrates(self.db)

    @property
    def plant_messages(self) -> list:
        """The messages the plant sends, in sending order (demand-only first, the trigger last)."""
        msgs = []
        for q in ("demand_torque_nm", "train_speed_ms", "motor_speed_rad_s"):
            m = self.where[q][0]
            if m in msgs:
                msgs.remove(m)
            msgs.append(m)
        return msgs

    @property
    def command_message(self):
        return self.where["torque_command_nm"][0]


def resolve_dbc(scenario_path, dbc: str) -> Path:
    """The file ``[bus] dbc`` names: relative to the scenario file's directory unless absolute."""
    path = Path(dbc)
    return path if path.is_absolute() else Path(scenario_path).resolve().parent / path


def scenario_dbc(scenario) -> Path:
    """The DBC a scenario's bus speaks: its ``[bus] dbc`` (``resolve_dbc``), or the HIL's own ``hil/hil.dbc``."""
    return resolve_dbc(scenario.path, scenario.bus.dbc) if scenario.bus.dbc else DBC_PATH


def load_mapping(scenario_path, dbc: str, table: dict, period_s: float, needs: dict[str, Need] | None = None,
                 text: str | None = None) -> Mapping:
    """Their DBC (``dbc``, a path relative to the scenario file's directory unless absolute) and the
    ``[bus.mapping]`` table, checked: each quantity named once as ``Message.Signal`` of that DBC,
    no multiplexed message, the command in a message the plant does not send, no id of the HIL frames
    that still travel (``RESERVED_IDS``), cycle times matching ``period_s``, and each signal able to
    carry ``needs``.  ``text``: the DBC's text itself (a log keeps it), not read from ``dbc``.
    ``ConfigError`` (one line naming the file and the key) otherwise."""
    import cantools

    path = resolve_dbc(scenario_path, dbc)

    def fail(key, msg):
        return ConfigError(f"{scenario_path}: {key}: {msg}")

    try:
        if text is not None:
            db = cantools.database.load_string(text, database_format="dbc", strict=True)
        else:
            db = cantools.database.load_file(str(path), database_format="dbc", strict=True)
    except FileNotFoundError:
        raise fail("[bus] dbc", f"no such file {str(path)!r}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise fail("[bus] dbc", f"cannot read {str(path)!r}: {e}") from None
    except Exception as e:  # noqa: BLE001 - cantools' parse errors have no common base we can name
        raise fail("[bus] dbc", f"{path.name} is not a DBC cantools can read: "
                   f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    if not isinstance(table, dict):
        raise fail("[bus.mapping]", "must be a table of QUANTITY = \"Message.Signal\"")
    for key in table:
        if key not in QUANTITIES and key != TCU_FRAMES:
            raise fail(f"[bus.mapping] {key}", f"unknown quantity (known: {', '.join(QUANTITIES)}; and {TCU_FRAMES}, "
                       "the TCU's other messages)")
    where = {}
    for q in QUANTITIES:
        key = f"[bus.mapping] {q}"
        if q not in table:
            raise fail(key, f"missing: a mapped bus names the message and signal of each of {', '.join(QUANTITIES)}")
        text = table[q]
        if not isinstance(text, str) or text.count(".") != 1:
            raise fail(key, f"must be \"Message.Signal\" of {path.name}, got {text!r}")
        mname, sname = text.split(".")
        try:
            m = db.get_message_by_name(mname)
        except KeyError:
            raise fail(key, f"no message {mname!r} in {path.name} (messages: "
                       f"{', '.join(x.name for x in db.messages) or 'none'})") from None
        try:
            s = m.get_signal_by_name(sname)
        except KeyError:
            raise fail(key, f"message {mname} of {path.name} has no signal {sname!r} (signals: "
                       f"{', '.join(x.name for x in m.signals)})") from None
        if m.is_multiplexed() or m.is_container:
            raise fail(key, f"message {mname} of {path.name} is multiplexed: not supported")
        if m.frame_id in RESERVED_IDS and not m.is_extended_frame:
            raise fail(key, f"message {mname} of {path.name} has id 0x{m.frame_id:X}, the id of the HIL's "
                       f"{RESERVED_IDS[m.frame_id]} frame, which still travels on a mapped bus")
        if m.cycle_time and abs(m.cycle_time * 1e-3 - period_s) > 1e-9:
            raise fail(key, f"message {mname} of {path.name} has a cycle time of {m.cycle_time} ms (GenMsgCycleTime); "
                       f"the scenario's exchange period is {period_s * 1e3:g} ms: set run.exchange_period_s = "
                       f"{m.cycle_time * 1e-3:g} (--set run.exchange_period_s={m.cycle_time * 1e-3:g}) or the "
                       "message's GenMsgCycleTime to the period")
        if needs is not None:
            lo, hi = signal_span(s)
            need = needs[q]
            if lo > need.lo + 1e-12 or hi < need.hi - 1e-12:
                raise fail(key, f"signal {text} carries {lo:g} .. {hi:g} {s.unit or ''}".rstrip()
                           + f", too narrow for this scenario ({need.why}: {need.lo:g} .. {need.hi:.6g})")
        where[q] = (m, s.name)
    command = where["torque_command_nm"][0]
    if any(where[q][0] is command for q in SENT):
        raise fail("[bus.mapping] torque_command_nm", f"message {command.name} also carries a quantity the plant "
                   "sends; the command needs a message of its own")
    return Mapping(str(path), db, where, _tcu_frames(table.get(TCU_FRAMES, ()), db, where, path, fail))


def _tcu_frames(names, db, where, path, fail) -> tuple:
    """The messages ``tcu_frames`` names, checked: each a message of the DBC, once, not multiplexed, not the
    command or a message the plant sends, not on a HIL frame's id (each has its own id: a DBC names each id
    once)."""
    key = f"[bus.mapping] {TCU_FRAMES}"
    if isinstance(names, str) or not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise fail(key, f"must be a list of message names of {path.name}, got {names!r}")
    taken = {m.name: q for q, (m, _) in where.items()}
    out = []
    for name in names:
        try:
            m = db.get_message_by_name(name)
        except KeyError:
            raise fail(key, f"no message {name!r} in {path.name} (messages: "
                       f"{', '.join(x.name for x in db.messages) or 'none'})") from None
        if name in taken:
            raise fail(key, f"message {name} carries {taken[name]} already: a TCU frame is another message")
        if m in out:
            raise fail(key, f"message {name} is named twice")
        if m.is_multiplexed() or m.is_container:
            raise fail(key, f"message {name} of {path.name} is multiplexed: not supported")
        if m.frame_id in RESERVED_IDS and not m.is_extended_frame:
            raise fail(key, f"message {name} of {path.name} has id 0x{m.frame_id:X}, the id of the HIL's "
                       f"{RESERVED_IDS[m.frame_id]} frame, which still travels on a mapped bus")
        out.append(m)
    return tuple(out)


def _clip(sig, value: float) -> float:
    lo, hi = signal_span(sig)
    return min(max(value, lo), hi)


class MappedCodec:
    """The frames of a mapped bus, with ``FrameCodec``'s interface where the nodes use it.

    ``sensor_frames`` / ``command`` build their mapped messages; the HIL frames (heartbeats,
    identification frames) go through ``hil`` (a ``FrameCodec`` over ``hil/hil.dbc``, unauthenticated).
    ``classify`` decodes a mapped message (cantools, ``scaling=True``) into what the HIL frames would
    carry: a ``PlantSensor`` frame for the trigger message (its ``demand`` attached when the trigger
    carries it), ``DriverDemand`` for a demand-only message, ``TorqueCommand`` for the command (its step
    -1: the plant node dates it).  Steps on the TCU side count trigger frames from ``restart()``."""

    mapped = True

    def __init__(self, period_s: float, mapping: Mapping):
        self.mapping = mapping
        self.hil = FrameCodec(period_s)
        self.db = self.hil.db
        self.period_s = period_s
        self.auth = None
        self._sent = mapping.plant_messages
        self._trigger = self._sent[-1]
        self._by_id = {m.frame_id: m for m in [*self._sent, mapping.command_message, *mapping.tcu_frames]}
        self._by_key = {(bool(m.is_extended_frame), m.frame_id): m for m in self._by_id.values()}
        self.command_id = mapping.command_message.frame_id
        #: the ids of the TCU's frames: its command and its other messages (``tcu_frames``)
        self.tcu_ids = frozenset([self.command_id, *(m.frame_id for m in mapping.tcu_frames)])
        self._tcu_frames = frozenset(m.frame_id for m in mapping.tcu_frames)
        #: "Message.Signal" -> frames received with that signal outside its DBC range (every signal of a
        #: message received listed, from its first frame on)
        self.out_of_range: dict[str, int] = {}
        self.plant_ids = frozenset(m.frame_id for m in self._sent)
        self._fill = {m.frame_id: {s.name: _clip(s, s.initial if s.initial is not None else 0.0) for s in m.signals}
                      for m in self._by_id.values()}
        #: the mapped signals of each message (checked against their DBC range on receipt)
        self._mapped = {fid: [sname for mm, sname in mapping.where.values() if mm.frame_id == fid] for fid in self._by_id}
        self._values: dict[str, float] = {}
        self._step = 0

    def restart(self) -> None:
        """Count readings from 0 again (the TCU side, when the plant's run starts)."""
        self._step = 0

    # -- encoding ----------------------------------------------------------------------------------
    def _msg(self, m, quantities: dict) -> can.Message:
        values = dict(self._fill[m.frame_id])
        for q, x in quantities.items():
            mm, sname = self.mapping.where[q]
            if mm is m:
                values[sname] = _clip(m.get_signal_by_name(sname), x)
        data = m.encode(values, scaling=True, padding=False, strict=False)
        return can.Message(arbitration_id=m.frame_id, data=data, is_extended_id=m.is_extended_frame,
                           is_fd=bool(m.is_fd), bitrate_switch=bool(m.is_fd))

    def sensor_frames(self, demand: DriverDemand, reading: SensorReading) -> list[can.Message]:
        """The plant's frames of one period, in sending order (the trigger last)."""
        q = {"motor_speed_rad_s": reading.motor_speed_rad_s, "train_speed_ms": reading.train_speed_ms,
             "demand_torque_nm": demand.torque_nm}
        return [self._msg(m, q) for m in self._sent]

    def command(self, c: TorqueCommand) -> can.Message:
        return self._msg(self.mapping.command_message, {"torque_command_nm": c.torque_nm})

    def status(self, st, obs):
        return self.hil.status(st, obs)

    def result(self, e):
        return self.hil.result(e)

    def interval(self, e):
        return self.hil.interval(e)

    def estimate(self, e):
        return self.hil.estimate(e)

    def sample(self, r):
        return self.hil.sample(r)

    def plant_heartbeat(self, counter: int, state: int, step: int) -> can.Message:
        return self.hil.plant_heartbeat(counter, state, step)

    def tcu_heartbeat(self, counter: int, state: int, step: int) -> can.Message:
        return self.hil.tcu_heartbeat(counter, state, step)

    # -- decoding ----------------------------------------------------------------------------------
    def classify(self, msg: can.Message) -> tuple[Frame | None, str]:
        """(Frame, "ok") or (None, reason), as ``FrameCodec.classify``; never raises."""
        m = self._by_key.get((bool(msg.is_extended_id), msg.arbitration_id))
        if m is None or msg.is_error_frame or msg.is_remote_frame:
            if msg.arbitration_id in (SENSOR_ID, DEMAND_ID, COMMAND_ID) and not msg.is_extended_id:
                return None, "unknown_id"          # the HIL frames a mapped bus replaces
            frame, status = self.hil.classify(msg)
            if status == "unknown_id" and not (msg.is_error_frame or msg.is_remote_frame):
                return None, unmapped_status(msg)  # an id the mapping does not name: counted by id
            return frame, status
        data = bytes(msg.data)
        if len(data) != m.length:
            return None, "bad_length"
        try:
            v = m.decode(data, decode_choices=False, scaling=True)
        except Exception as e:  # noqa: BLE001 - a frame must never crash a node
            return None, f"undecodable:{type(e).__name__}"
        outside = self._range_check(m, v)
        for sname in self._mapped[m.frame_id]:
            if sname in outside:
                return None, f"out_of_range:{sname}"
        if m.frame_id in self._tcu_frames:
            return Frame("TcuFrame", (m.name, v)), "ok"
        if m is self.mapping.command_message:
            return Frame("TorqueCommand", TorqueCommand(-1, float(v[self.mapping.where["torque_command_nm"][1]]))), "ok"
        for q in SENT:
            mm, sname = self.mapping.where[q]
            if mm is m:
                self._values[q] = float(v[sname])
        demand = None
        if self.mapping.where["demand_torque_nm"][0] is m and "demand_torque_nm" in self._values:
            demand = DriverDemand(self._step, self._values["demand_torque_nm"])
        if m is not self._trigger:
            return (Frame("DriverDemand", demand), "ok") if demand is not None else (Frame("MappedPart", None), "ok")
        if "train_speed_ms" not in self._values:
            return None, "incomplete_reading"
        reading = SensorReading(self._step, self._values["motor_speed_rad_s"], self._values["train_speed_ms"])
        self._step += 1
        return Frame("PlantSensor", reading, demand), "ok"


    def _range_check(self, m, values: dict) -> set:
        """The signals of message ``m`` whose decoded ``values`` lie outside their DBC minimum .. maximum,
        each counted in ``out_of_range`` (every signal of ``m`` listed there from its first frame on)."""
        outside = set()
        for sig in m.signals:
            key = f"{m.name}.{sig.name}"
            x = values.get(sig.name)
            n = self.out_of_range.setdefault(key, 0)
            if isinstance(x, (int, float)) and ((sig.minimum is not None and x < sig.minimum)
                                                 or (sig.maximum is not None and x > sig.maximum)):
                self.out_of_range[key] = n + 1
                outside.add(sig.name)
        return outside


def unmapped_status(msg) -> str:
    """The status of a frame whose id a mapping does not name: ``unmapped_id:0x123`` (extended ids with 8
    hex digits), counted by id in the run summary's ``unmapped_ids``."""
    return f"unmapped_id:0x{msg.arbitration_id:08X}" if msg.is_extended_id else f"unmapped_id:0x{msg.arbitration_id:X}"


def codec_for(scenario, period_s: float | None = None, auth=None, dbc_text: str | None = None):
    """The codec of a scenario's bus: ``FrameCodec`` over ``hil/hil.dbc``, or ``MappedCodec`` when its
    ``[bus]`` names a DBC of its own (never authenticated; ``dbc_text``: that DBC's text, as a log keeps it)."""
    period = scenario.run.exchange_period_s if period_s is None else period_s
    settings = scenario.bus
    if not settings.dbc:
        return FrameCodec(period, auth=auth)
    return MappedCodec(period, load_mapping(scenario.path, settings.dbc, dict(settings.mapping), period,
                                            text=dbc_text))


def classic_frame_time_s(data_len: int, bitrate: int) -> float:
    """Worst-case duration (s) of a classical CAN base-format data frame with ``data_len`` bytes: 44 bits of
    frame around ``8 n`` data bits, and at worst a stuff bit per 4 bits of the 34 + 8 n stuffed ones."""
    return (44 + 8 * data_len + (34 + 8 * data_len - 1) // 4) / bitrate


def mapped_bus_load(mapping: Mapping, period_s: float, bitrate: int) -> float:
    """The mapped frames' share of a classical bus at ``bitrate`` (percent): each mapped message once a period."""
    msgs = [*mapping.plant_messages, mapping.command_message]
    return 100.0 * sum(classic_frame_time_s(m.length, bitrate) for m in msgs) / period_s
