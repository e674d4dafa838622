"""The DBC frames: exact round trips through cantools, validation of malformed frames, bus load."""
import math
import random
import struct

import can
import cantools
import numpy as np
import pytest

from hil.bus.frames import (IntervalReport, COMMAND_ID, DBC_PATH, PLANT_HEARTBEAT_ID, RESULT_ID, SENSOR_ID, STATUS_ID, TCU_HEARTBEAT_ID,
                        FrameCodec, bus_load, fd_frame_time_s, load_dbc)
from hil.config import load_scenario
from hil.tcu_node import TcuNode
from identifier.messages import IdentificationEvent, ObserverSample, SensorReading, TcuStatus, TorqueCommand

from .conftest import case_seed

PERIOD = 1e-3


@pytest.fixture(scope="module")
def codec():
    return FrameCodec(PERIOD)


def fd(fid, data, **kw):
    return can.Message(arbitration_id=fid, data=bytes(data), is_extended_id=False, is_fd=True, **kw)


def test_dbc_declares_can_fd_frames_with_fixed_ids():
    db = cantools.database.load_file(str(DBC_PATH))
    by_name = {m.name: m for m in db.messages}
    assert by_name["PlantSensor"].frame_id == 0x100 and by_name["PlantSensor"].length == 32
    assert by_name["TorqueCommand"].frame_id == 0x110 and by_name["TorqueCommand"].length == 20
    assert by_name["TcuStatus"].length == 48 and by_name["TcuResult"].length == 64
    assert all(m.is_fd for m in db.messages)
    # every frame ends its signals with the 8-byte authentication trailer (hil/bus/secoc.py)
    for m in db.messages:
        fv, mac = m.get_signal_by_name("AuthFreshness"), m.get_signal_by_name("AuthMac")
        assert (fv.length, mac.length, mac.start) == (16, 48, fv.start + 16), m.name
        assert all(s.start + s.length <= fv.start for s in m.signals if s not in (fv, mac)), m.name
        assert fv.start + 64 <= 8 * m.length, m.name
    # measured speeds travel as IEEE doubles: the bus adds no quantisation
    assert by_name["PlantSensor"].get_signal_by_name("MotorSpeed").is_float
    assert by_name["PlantSensor"].get_signal_by_name("MotorSpeed").length == 64


def test_sensor_frame_layout_is_little_endian_step_then_doubles(codec):
    msg = codec.sensor(SensorReading(513, 63.75, 10.125))
    assert msg.is_fd and msg.bitrate_switch and not msg.is_extended_id and msg.arbitration_id == 0x100
    assert bytes(msg.data[:4]) == struct.pack("<I", 513)
    assert struct.unpack("<dd", bytes(msg.data[4:20])) == (63.75, 10.125)


def test_every_message_round_trips_exactly(codec):
    rng = np.random.default_rng(0)
    for _ in range(200):
        k = int(rng.integers(0, 2**31))
        r = SensorReading(k, float(rng.uniform(-1000, 1000)), float(rng.uniform(-100, 100)))
        f, status = codec.classify(codec.sensor(r))
        assert status == "ok" and f.value == r
        c = TorqueCommand(k, float(rng.uniform(-1e5, 1e5)))
        assert codec.classify(codec.command(c))[0].value == c
        st = TcuStatus(k, int(rng.integers(0, 4)), int(rng.integers(0, 65536)))
        obs = ObserverSample(k, k * PERIOD, float(rng.normal()), float(rng.normal()), float(rng.normal() * 1e4))
        f, _ = codec.classify(codec.status(st, obs))
        assert f.value == (st, obs)
        assert codec.classify(codec.status(st, None))[0].value == (st, None)
        params = tuple(float(x) for x in rng.normal(size=5))
        e = IdentificationEvent(k, k * PERIOD, "correction", 7, params, 0.25, 300)
        assert codec.classify(codec.result(e))[0].value == e


def test_intervals_and_samples_round_trip_and_pair_with_their_result(codec, ffcc_a):
    """A result's 90 % intervals travel in a TcuInterval frame right after it; the trace pairs them by
    (step, correction, kind) and a result is final once the status of its step arrived."""
    from hil.bus.frames import SampleReport
    from hil.trace import Trace

    e = IdentificationEvent(812, 812 * PERIOD, "unconfirmed", 3, (0.0, 0.6, -0.6, -0.5, -1.1), 0.5, 40,
                            (0.141, 0.163), (1.05, 1.52))
    r, i = codec.classify(codec.result(e))[0], codec.classify(codec.interval(e))[0]
    assert r.value.kind == "unconfirmed" and i.name == "TcuInterval"
    assert (i.value.peak_mu_ci, i.value.peak_creep_ci, i.value.level_percent) == ((0.141, 0.163), (1.05, 1.52), 90)
    assert codec.interval(IdentificationEvent(1, PERIOD, "correction", 1, (0.0, 0.6, -0.6, -0.5, -1.1), 0.0, 9)) is None
    s = SampleReport(812, 17, 790, 0.734, 0.1337)
    assert codec.classify(codec.sample(s))[0].value == s
    trace = Trace(ffcc_a)
    trace.result(r.value)
    other = IntervalReport(812, 2, "unconfirmed", 90, (0.0, 1.0), (0.0, 1.0))
    assert not trace.interval(other) and trace.interval(i.value)
    assert trace.settle(811) == [] and trace.events == []
    assert trace.settle(812) == [e] and trace.events == [e]
    assert trace.events[0].peak_mu_ci == (0.141, 0.163) and trace.events[0].peak_creep_ci == (1.05, 1.52)


def test_an_open_interval_crosses_the_bus_flagged(codec, ffcc_a):
    """IntervalOpen (TcuInterval's byte 40): an interval whose upper ends are the TCU's working range
    arrives flagged, through the compiled layout and through cantools' decoding of the DBC, with and
    without authentication, and the trace keeps the flag on the event; a flag other than 0 or 1 is refused."""
    from hil.bus.frames import INTERVAL_ID
    from hil.trace import Trace

    key = bytes(range(16))
    tcu, plant = FrameCodec(PERIOD, auth=key), FrameCodec(PERIOD, auth=key)
    for open_ in (False, True):
        e = IdentificationEvent(640, 0.64, "correction", 12, (0.0, 0.6, -0.6, -0.5, -1.1), 0.5, 140,
                                (0.1483, 0.1502), (2.77, 3.0), peak_open=open_)
        for sender, receiver in ((codec, codec), (tcu, plant)):
            msg = sender.interval(e)
            assert len(msg.data) == 64 and msg.data[40] == int(open_)
            assert codec.db.decode_message(INTERVAL_ID, bytes(msg.data), decode_choices=False)["IntervalOpen"] == int(open_)
            frame, status = receiver.classify(msg)
            assert status == "ok" and frame.value.peak_open is open_
            assert frame.value.peak_creep_ci == (2.77, 3.0)
        trace = Trace(ffcc_a)
        trace.result(codec.classify(codec.result(e))[0].value)
        assert trace.interval(codec.classify(codec.interval(e))[0].value)
        assert trace.settle() == [e] and trace.events[0].peak_open is open_
    data = bytearray(codec.interval(e).data)
    data[40] = 2
    assert codec.classify(fd(INTERVAL_ID, data)) == (None, "out_of_range:IntervalOpen")


def test_result_frame_carries_inf_and_nan_scores(codec):
    e = IdentificationEvent(9, 9 * PERIOD, "confirmed", 3, (0.1, 0.2, 0.3, -0.4, -0.5), math.nan, 40)
    got = codec.classify(codec.result(e))[0].value
    assert math.isnan(got.j_ef) and got.params == e.params and got.kind == "confirmed"
    e2 = IdentificationEvent(9, 9 * PERIOD, "correction", 0, (0.1,), math.inf, 8)
    assert codec.classify(codec.result(e2))[0].value.j_ef == math.inf


def _sensor_bytes(step, omega, v):
    return struct.pack("<Idd", step, omega, v) + bytes(4) + bytes(8)     # + the (zero) authentication trailer


@pytest.mark.parametrize("msg, reason", [
    (fd(0x123, b"\xde\xad\xbe\xef"), "unknown_id"),
    (can.Message(arbitration_id=0x100, data=_sensor_bytes(1, 60.0, 10.0), is_extended_id=True, is_fd=True),
     "unknown_id"),
    (can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=False), "bad_length"),
    (fd(0x100, _sensor_bytes(1, 60.0, 10.0)[:20]), "bad_length"),
    (fd(0x100, _sensor_bytes(1, math.nan, 10.0)), "non_finite:MotorSpeed"),
    (fd(0x100, _sensor_bytes(1, 60.0, math.inf)), "non_finite:TrainSpeed"),
    (fd(0x100, _sensor_bytes(1, 60.0, -math.inf)), "non_finite:TrainSpeed"),
    (fd(0x100, _sensor_bytes(1, 1e6, 10.0)), "out_of_range:MotorSpeed"),
    (fd(0x110, struct.pack("<Id", 1, 1e9) + bytes(8)), "out_of_range:TorqueCmd"),
    (fd(0x120, struct.pack("<IBBHddd", 1, 9, 1, 0, 0.1, 1.0, 10.0) + bytes(16)), "out_of_range:Stage"),
    (can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=8, is_extended_id=False), "remote_frame"),
    (can.Message(arbitration_id=0x702, is_error_frame=True, is_extended_id=False), "error_frame"),
])
def test_malformed_frames_are_rejected_with_a_reason(codec, msg, reason):
    frame, status = codec.classify(msg)
    assert frame is None and status == reason


def test_random_frames_never_raise(codec):
    rng = np.random.default_rng(1)
    ids = [SENSOR_ID, COMMAND_ID, STATUS_ID, RESULT_ID, PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID, 0x7FF, 0x0]
    ok = 0
    for i in range(3000):
        n = int(rng.choice([0, 1, 8, 12, 20, 24, 32, 48, 64]))
        msg = can.Message(arbitration_id=int(rng.choice(ids)), data=rng.bytes(n), is_fd=n > 8,
                          is_extended_id=bool(i % 7 == 0))
        frame, status = codec.classify(msg)
        assert (frame is None) == (status != "ok")
        ok += status == "ok"
    assert ok < 3000


@pytest.fixture(scope="module")
def ffcc_a():
    return load_scenario("scenarios/ffcc_a.toml", {"run.duration_s": 0.62})


def _drive(node, scenario, garbage_every=None):
    """Feed the node the sensor frames of a deterministic trajectory (a synthetic slip after the fault),
    optionally with garbage frames in between; returns every reply frame's (id, data)."""
    from plant import SensorModel, WheelsetPlant
    plant = WheelsetPlant(scenario.plant_config())
    sensors = SensorModel(scenario.sensors, 5)
    codec = node.codec
    rng = np.random.default_rng(2)
    replies = []
    for k in range(scenario.steps):
        s = plant.state
        omega, v = sensors.measure(s.motor_speed_rad_s, s.train_speed_ms)
        if garbage_every and k % garbage_every == 0:
            for bad in (fd(0x100, _sensor_bytes(k + 1, math.nan, v)), fd(0x100, _sensor_bytes(k + 1, omega, 1e9)),
                        fd(0x100, _sensor_bytes(k + 1, omega, v)[:12]), fd(0x555, rng.bytes(8)),
                        fd(0x100, _sensor_bytes(k + 5000, omega, v))):      # a step from nowhere
                assert node.handle(bad) == []
        out = node.handle(codec.sensor(SensorReading(k, omega, v)))
        replies += [(m.arbitration_id, bytes(m.data)) for m in out]
        cmd = codec.classify(out[0])[0].value
        assert cmd.step == k
        plant.step(cmd.torque_nm)
    return replies


def test_garbage_never_reaches_the_identifier(ffcc_a):
    clean = TcuNode(ffcc_a, "nlls", 1)
    dirty = TcuNode(ffcc_a, "nlls", 1)
    replies_clean = _drive(clean, ffcc_a)
    replies_dirty = _drive(dirty, ffcc_a, garbage_every=10)
    assert replies_dirty == replies_clean
    assert clean.events > 0                           # the trajectory did produce identification events
    n = len(range(0, ffcc_a.steps, 10))
    assert dirty.rejected == {"non_finite:MotorSpeed": n, "out_of_range:TrainSpeed": n, "bad_length": n,
                              "unknown_id": n, "bad_sequence": n}
    assert dirty.identifier.rejected_readings == 0 and dirty.sensor_frames == ffcc_a.steps


def test_fd_frame_time_matches_a_hand_count():
    # 8 data bytes, 1 Mbit/s arbitration, 5 Mbit/s data.  Arbitration phase: SOF + 11 id + RRS, IDE, FDF,
    # res, BRS = 17 bits + 4 worst-case stuff bits; tail: CRC delimiter, ACK, ACK delimiter, 7 EOF, 3 IFS = 13.
    # Data phase: ESI + 4 DLC + 64 data = 69 bits + 17 stuff bits, 4-bit stuff count, CRC-17 and 6 fixed
    # stuff bits = 113 bits.
    expected = (17 + 4 + 13) / 1e6 + (69 + 17 + 4 + 17 + 6) / 5e6
    assert fd_frame_time_s(8, 1_000_000, 5_000_000) == pytest.approx(expected)
    # without bit-rate switch the data phase runs at the arbitration rate
    assert fd_frame_time_s(8, 1_000_000, 5_000_000, brs=False) == pytest.approx((17 + 4 + 13 + 113) / 1e6)


def test_bus_load_of_the_schedule():
    db = load_dbc()
    lengths = {m.frame_id: m.length for m in db.messages}
    load = bus_load(db, 1e-3, 2e-3, 1_000_000, 5_000_000)
    per_period = sum(fd_frame_time_s(lengths[i], 1_000_000, 5_000_000) for i in (0x100, 0x110, 0x120))
    per_period += fd_frame_time_s(64, 1_000_000, 5_000_000) / 10       # TcuEstimate, one in ten periods
    per_hb = sum(fd_frame_time_s(16, 1_000_000, 5_000_000) for _ in range(2))
    assert load["load_percent"] == pytest.approx(100 * (per_period / 1e-3 + per_hb / 2e-3))
    slow = bus_load(db, 1e-3, 2e-3, 250_000, 1_000_000)
    assert slow["load_percent"] > 70 > load["load_percent"]


def test_tcu_resyncs_after_losing_many_frames_but_not_on_single_garbage(ffcc_a):
    node = TcuNode(ffcc_a, "nlls", 1)
    c = node.codec
    for k in range(10):
        assert node.handle(c.sensor(SensorReading(k, 63.7, 10.0)))
    assert node.handle(c.sensor(SensorReading(5000, 63.7, 10.0))) == []      # a lone jump: garbage
    assert node.handle(c.sensor(SensorReading(10, 63.7, 10.0)))
    assert node.handle(c.sensor(SensorReading(900, 63.7, 10.0))) == []       # 889 frames lost ...
    assert node.handle(c.sensor(SensorReading(901, 63.7, 10.0)))             # ... and the stream goes on there
    assert node.handle(c.sensor(SensorReading(902, 63.7, 10.0)))
    assert node.rejected == {"bad_sequence": 2} and node.resyncs == 1 and node.last_step == 902


def test_tcu_never_resyncs_back_to_steps_it_answered(ffcc_a):
    """Two old sensor frames of consecutive steps sent again (a third node replaying what it saw, with
    frame authentication off) must not pull the TCU back: it would then reject the plant's next frames
    as out of sequence and the lockstep run would stall (found by ``hil bench robustness``, frames part,
    auth off, seed 12: the TCU back at step 562 while the plant waited at 753)."""
    node = TcuNode(ffcc_a, "nlls", 1)
    c = node.codec
    for k in range(300):
        assert node.handle(c.sensor(SensorReading(k, 63.7, 10.0)))
    assert node.handle(c.sensor(SensorReading(120, 63.7, 10.0))) == []       # replays of steps answered
    assert node.handle(c.sensor(SensorReading(121, 63.7, 10.0))) == []
    assert node.handle(c.sensor(SensorReading(122, 63.7, 10.0))) == []
    assert node.last_step == 299 and node.resyncs == 0
    assert node.handle(c.sensor(SensorReading(300, 63.7, 10.0)))             # the plant's next frame is taken
    assert node.rejected == {"bad_sequence": 3} and node.last_step == 300


def test_a_resent_reading_of_the_last_step_is_answered_with_the_same_command(ffcc_a):
    """The plant's lockstep resend (a new frame for the pending step after its command was lost):
    the TCU answers it again with the command it sent for that step, counts it as ``resent`` (not
    rejected), and its identifier does not see the reading twice."""
    node = TcuNode(ffcc_a, "nlls", 1)
    c = node.codec
    rng = np.random.default_rng(case_seed())
    last = int(rng.integers(5, 200))
    for k in range(last + 1):
        first = node.handle(c.sensor(SensorReading(k, 63.7 + 0.01 * k, 10.0)))
    again = node.handle(c.sensor(SensorReading(last, 63.7, 10.0)))
    assert len(again) == 1 and again[0].arbitration_id == COMMAND_ID
    assert c.classify(again[0])[0].value == c.classify(first[0])[0].value       # the same step and torque
    assert node.resent == 1 and node.rejected == {} and node.sensor_frames == last + 1
    assert node.report()["resent"] == 1
    assert node.handle(c.sensor(SensorReading(last + 1, 63.7, 10.0)))[0].arbitration_id == COMMAND_ID


def test_every_reason_a_frame_is_refused_for_is_in_the_one_verdict_table(codec):
    """hil/bus/verdicts.py is the one table: whatever the codec, the authenticator or a node answers
    for a frame is one of its verdicts (random garbage, another key's frames, every sequence case)."""
    import tempfile
    from pathlib import Path

    from hil.bus.secoc import read_key, write_key
    from hil.bus.verdicts import ACTED, PASSED, REJECTED, VERDICTS, kind, newest, sensor_sequence

    rng = np.random.default_rng(case_seed())
    seen = set()
    ids = [SENSOR_ID, COMMAND_ID, STATUS_ID, RESULT_ID, PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID, 0x7FF, 0x0]
    with tempfile.TemporaryDirectory() as d:
        key_a, key_b = (read_key(write_key(Path(d) / name)) for name in ("a.key", "b.key"))
    sender, receiver, stranger = (FrameCodec(1e-3, codec.db, auth=k) for k in (key_a, key_a, key_b))
    for c in (codec, receiver):
        for i in range(2000):
            n = int(rng.choice([0, 8, 20, 32, 48, 64]))
            msg = can.Message(arbitration_id=int(rng.choice(ids)), data=rng.bytes(n), is_fd=n > 8,
                              is_extended_id=bool(i % 7 == 0), is_error_frame=bool(i % 97 == 0))
            seen.add(c.classify(msg)[1])
    good = sender.sensor(SensorReading(1, 63.7, 10.0))
    verdicts = [receiver.classify(good)[1], receiver.classify(good)[1], stranger.classify(good)[1]]
    assert verdicts == ["ok", "replayed", "forged"]
    seen |= set(verdicts)
    seen |= {sensor_sequence(s, 10, 100) for s in (11, 10, 9, 200, -1)}
    assert {sensor_sequence(11, 10, 100), sensor_sequence(10, 10, 100), sensor_sequence(9, 10, 100)} == \
        {"ok", "resent", "bad_sequence"}
    assert sensor_sequence(0, -1, 100) == "ok" and sensor_sequence(-1, -1, 100) == "bad_sequence"
    assert newest({0: 5, 3: 7, 4: 6}) == {0, 4} and newest({}) == set()
    print(sorted(seen))
    for verdict in seen:
        assert verdict.split(":", 1)[0] in VERDICTS, verdict
    assert {kind(v) for v in VERDICTS} == {ACTED, PASSED, REJECTED}
    assert kind("forged") == REJECTED and kind("late") == PASSED and kind("non_finite:MotorSpeed") == REJECTED
    assert kind("no such verdict") == REJECTED


def test_compiled_layouts_give_cantools_bytes_and_values_for_every_frame(codec):
    """The struct layouts compiled from the DBC encode and decode as cantools does, for random values
    across each signal's whole range (ints to their limits, floats of any magnitude, infinities)."""
    seed = case_seed()
    rng = random.Random(seed)
    assert all(codec.layouts[fid] is not None for fid in codec.layouts)   # every frame of hil.dbc compiles
    for m in codec.db.messages:
        layout = codec.layouts[m.frame_id]
        assert set(layout.names) == {s.name for s in m.signals} - {"AuthFreshness", "AuthMac"}
        for _ in range(200):
            values = {}
            for s in m.signals:
                if s.name in ("AuthFreshness", "AuthMac"):
                    continue
                if s.is_float:
                    values[s.name] = rng.choice([rng.uniform(-1e3, 1e3), rng.uniform(-1e300, 1e300) if s.length == 64
                                                 else rng.uniform(-3e38, 3e38), math.inf, -math.inf, 0.0])
                else:
                    lo, hi = (-(2 ** (s.length - 1)), 2 ** (s.length - 1) - 1) if s.is_signed else (0, 2**s.length - 1)
                    values[s.name] = rng.choice([lo, hi, rng.randint(lo, hi)])
            want = m.encode({**values, "AuthFreshness": 0, "AuthMac": 0}, scaling=True, padding=False, strict=False)
            got = layout.pack(values)
            assert got == bytes(want), (m.name, values)
            decoded = m.decode(want, decode_choices=False, scaling=True)
            assert dict(zip(layout.names, layout.unpack(got))) == {k: decoded[k] for k in layout.names}
    # a value the layout cannot hold goes to cantools, which rounds it as IEEE float32 does
    msg = codec.result(IdentificationEvent(3, 0.003, "correction", 1, (0.3, 1.2), 1e39, 5))
    frame, verdict = codec.classify(msg)
    assert verdict == "ok" and frame.value.j_ef == math.inf and msg.arbitration_id == RESULT_ID


def test_the_command_leaves_before_the_strategy_works(ffcc_a):
    """``handle(..., send=)`` hands the TorqueCommand out before the drill and the strategy see the
    reading (the plant waits for the command only): the same frames as without ``send``, command first,
    and when it is sent the strategy has not yet taken that reading's sample."""
    from plant import SensorModel, WheelsetPlant
    plain, early = TcuNode(ffcc_a, "proposed", 1), TcuNode(ffcc_a, "proposed", 1)
    plant = WheelsetPlant(ffcc_a.plant_config())
    sensors = SensorModel(ffcc_a.sensors, 5)
    took_later = 0
    for k in range(ffcc_a.steps):
        s = plant.state
        reading = SensorReading(k, *sensors.measure(s.motor_speed_rad_s, s.train_speed_ms))
        whole = plain.handle(plain.codec.sensor(reading))
        before = early.identifier.strategy.samples
        sent = []
        rest = early.handle(early.codec.sensor(reading),
                            send=lambda m: sent.append((m, early.identifier.strategy.samples)))
        assert len(sent) == 1 and sent[0][1] == before, f"step {k}"
        assert [(m.arbitration_id, bytes(m.data)) for m in [sent[0][0]] + rest] == \
            [(m.arbitration_id, bytes(m.data)) for m in whole], f"step {k}"
        took_later += early.identifier.strategy.samples > before
        plant.step(early.codec.classify(sent[0][0])[0].value.torque_nm)
    assert took_later > 10          # the slip did feed the strategy, each sample after its command


def test_compiled_decoders_judge_and_decode_as_the_dict_path(codec):
    """``classify``'s compiled path (every frame of hil.dbc) gives the verdict and the object the dict path
    gives, on random payloads of every id and on the edges: NaN, infinities, bounds and just beyond."""
    slow = FrameCodec(PERIOD, codec.db)
    slow._fast = {}                      # the dict path alone
    assert set(codec._fast) == {fid for fid, layout in codec.layouts.items() if layout is not None}
    rng = random.Random(case_seed("payloads"))
    edges = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1e300, -1e300]
    seen = set()
    for fid, m in codec._by_id.items():
        layout = codec.layouts[fid]
        for i in range(400):
            data = bytearray(rng.randbytes(m.length))
            if i % 2:        # a valid frame of random values, half the time one signal at an edge or a limit
                values = {}
                for n in layout.names:
                    sig = m.get_signal_by_name(n)
                    lo = sig.minimum if sig.minimum is not None else -1e6
                    hi = sig.maximum if sig.maximum is not None else 1e6
                    values[n] = rng.uniform(lo, hi) if sig.is_float else rng.randint(int(lo), int(hi))
                sig = m.get_signal_by_name(rng.choice(layout.names))
                if sig.is_float and i % 4 == 1:
                    choices = edges + [x for x in (sig.minimum, sig.maximum) if x is not None]
                    x = rng.choice(choices)
                    if rng.random() < 0.3 and math.isfinite(x) and x != 0:
                        x = math.nextafter(x, math.copysign(math.inf, x))
                    values[sig.name] = x
                try:
                    data = bytearray(layout.pack(values)) + bytes(m.length - layout.struct.size)
                except (OverflowError, struct.error):      # 1e300 in a 32-bit float: not a frame
                    continue
            msg = fd(fid, data)
            fast, slow_out = codec.classify(msg), slow.classify(msg)
            assert fast[1] == slow_out[1], (hex(fid), bytes(data).hex())
            seen.add(fast[1].split(":")[0])
            if fast[0] is not None:
                a, b = fast[0].value, slow_out[0].value
                assert repr(a) == repr(b), (hex(fid), a, b)      # repr: NaN fields compare equal
    assert {"ok", "non_finite", "out_of_range"} <= seen


def test_the_span_of_a_results_samples_crosses_the_bus(codec, ffcc_a):
    """SamplesStated / SamplesFromStep / SamplesToStep (TcuInterval): the span of the samples a result rests on
    arrives as the TCU stated it and the trace keeps it on the event; a result that states none (an older TCU's, an
    older log's frame: those bytes zero) arrives with NaN."""
    from hil.bus.frames import INTERVAL_ID
    from hil.trace import Trace

    stated = IdentificationEvent(640, 0.64, "confirmed", 12, (0.0, 0.6, -0.6, -0.5, -1.1), math.nan, 140,
                                 (0.1483, 0.1502), (2.77, 3.0), samples_from_s=0.501, samples_to_s=0.64)
    msg = codec.interval(stated)
    v = codec.db.decode_message(INTERVAL_ID, bytes(msg.data), decode_choices=False)
    assert (v["SamplesStated"], v["SamplesFromStep"], v["SamplesToStep"]) == (1, 501, 640)
    report = codec.classify(msg)[0].value
    assert report.samples_from_s == pytest.approx(0.501) and report.samples_to_s == pytest.approx(0.64)
    trace = Trace(ffcc_a)
    trace.result(codec.classify(codec.result(stated))[0].value)
    assert trace.interval(report)
    (e,) = trace.settle()
    assert e.samples_from_s == pytest.approx(0.501) and e.samples_to_s == pytest.approx(0.64)
    unstated = codec.interval(IdentificationEvent(640, 0.64, "confirmed", 12, (0.0, 0.6, -0.6, -0.5, -1.1), math.nan,
                                                  140, (0.1483, 0.1502), (2.77, 3.0)))
    assert bytes(unstated.data[41:50]) == bytes(9)
    r = codec.classify(unstated)[0].value
    assert math.isnan(r.samples_from_s) and math.isnan(r.samples_to_s)
