"""Frame authentication (hil/bus/secoc.py): a node without the key cannot forge a frame, a genuine frame
sent again is a replay, and on the embedded bus a run is authenticated by default, so a third node's
forged result, command and heartbeat and its replays change nothing and are counted by reason."""
import json
import os
import stat
import subprocess
import time

import can
import numpy as np
import pytest

from hil.errors import ConfigError
from hil.bus.frames import COMMAND_ID, SENSOR_ID, STATE_RUNNING, FrameCodec
from hil.bus.localbus import create_channel, remove_channel
from hil.bus.secoc import read_key, write_key
from identifier.messages import IdentificationEvent, SensorReading, TorqueCommand

from .conftest import ROOT, case_seed, hil_command, subprocess_env

PERIOD = 1e-3


def fresh_seed(what: str) -> int:
    return case_seed(what)


def pair(key=None):
    key = key or os.urandom(16)
    return FrameCodec(PERIOD, auth=key), FrameCodec(PERIOD, auth=key)


def test_genuine_frames_pass_replays_and_forgeries_do_not():
    tx, rx = pair()
    sent = [tx.sensor(SensorReading(k, 60.0 + k, 10.0)) for k in range(5)]
    for k, m in enumerate(sent[:3]):
        frame, status = rx.classify(m)
        assert status == "ok" and frame.value == SensorReading(k, 60.0 + k, 10.0)
    assert rx.classify(sent[2])[1] == "replayed"           # the last accepted frame again
    assert rx.classify(sent[0])[1] == "replayed"           # an older one
    assert rx.classify(sent[4])[1] == "ok"                 # a frame lost in between (sent[3]) leaves a gap only
    assert rx.classify(sent[3])[1] == "replayed"           # ... and arrives too late
    outsider = FrameCodec(PERIOD, auth=os.urandom(16))     # a node with another key
    assert rx.classify(outsider.sensor(SensorReading(9, 60.0, 10.0)))[1] == "forged"
    plain = FrameCodec(PERIOD)                             # a node that does not authenticate (zero trailer)
    assert rx.classify(plain.sensor(SensorReading(9, 60.0, 10.0)))[1] == "forged"
    assert rx.classify(tx.sensor(SensorReading(9, 60.0, 10.0)))[1] == "ok"


def test_any_altered_byte_is_a_forgery():
    seed = fresh_seed("altered bytes")
    g = np.random.default_rng(seed)
    tx, rx = pair()
    for i in range(200):
        m = tx.command(TorqueCommand(i, float(g.uniform(0, 3000))))
        data = bytearray(m.data)
        at = int(g.integers(len(data)))
        data[at] ^= 1 << int(g.integers(8))
        bad = can.Message(arbitration_id=COMMAND_ID, data=bytes(data), is_fd=True, is_extended_id=False)
        assert rx.classify(bad)[1] == "forged", (i, at)
        assert rx.classify(m)[1] == "ok"                   # the genuine frame still passes after it


def test_freshness_survives_the_16_bit_wrap_and_lost_frames():
    seed = fresh_seed("lost frames")
    g = np.random.default_rng(seed)
    tx, rx = pair()
    k = 0
    while k < 70_000:                                      # past 2^16 frames of one id
        gap = int(g.integers(1, 3000))
        for _ in range(gap - 1):
            tx.command(TorqueCommand(k, 1.0))               # sent but never received
            k += 1
        m = tx.command(TorqueCommand(k, 2.0))
        k += 1
        frame, status = rx.classify(m)
        assert status == "ok" and frame.value.step == k - 1


def test_key_file_is_private_and_checked(tmp_path):
    path = write_key(tmp_path / "k")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and len(read_key(path)) == 16
    with pytest.raises(FileExistsError):
        write_key(path)                                    # never overwritten
    (tmp_path / "short").write_text("abcd\n")
    with pytest.raises(ConfigError, match="bus.auth_key_file"):
        read_key(tmp_path / "short")
    with pytest.raises(ConfigError, match="bus.auth_key_file"):
        read_key(tmp_path / "missing")


def _run(tmp_path, channel, *extra):
    return subprocess.Popen(hil_command() + ["run", "scenarios/ffcc_a.toml", "--bus", f"localbus:{channel}",
                                             "--out", str(tmp_path), "--no-rrd", "--json",
                                             "--set", "run.duration_s=3", "--set", "run.fault_time_s=2.5", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(),
                            cwd=ROOT)


def test_a_third_node_without_the_key_changes_nothing_and_is_counted(tmp_path):
    """On the embedded bus authentication is on by default: a third node replays a command and a
    sensor frame it saw, and forges a result before the fault, a command and a heartbeat far ahead.
    Each is rejected where it arrives (counted as replayed / forged), nothing is 'suspicious', and
    the identification is the clean run's."""
    seed = fresh_seed("forging step")
    at_step = 200 + seed % 600
    clean_dir, dirty_dir = tmp_path / "clean", tmp_path / "dirty"
    channel = create_channel()
    try:
        proc = _run(clean_dir, channel)
        clean, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
    finally:
        remove_channel(channel)
    channel = create_channel()
    spy = can.Bus(interface="localbus", channel=channel)
    proc = None
    try:
        proc = _run(dirty_dir, channel)
        codec = FrameCodec(PERIOD)                         # the third node has no key
        end = time.monotonic() + 120
        k = None
        sensor = None
        while time.monotonic() < end and proc.poll() is None:
            msg = spy.recv(0.5)
            if msg is None:
                continue
            if msg.arbitration_id == SENSOR_ID:
                sensor = msg
            if msg.arbitration_id != COMMAND_ID or sensor is None:
                continue
            frame, _ = codec.classify(msg)                 # read without checking: the payload is not secret
            if frame is not None and frame.value.step >= at_step:
                k = frame.value.step
                spy.send(msg)                                                        # a replayed command
                spy.send(sensor)                                                     # a replayed sensor frame
                spy.send(codec.command(TorqueCommand(k + 1, 5000.0)))                # a forged command
                spy.send(codec.result(IdentificationEvent(k, k * 1e-3, "confirmed", 0, (0.3, 0.1, 0.2, 1.0, 5.0),
                                                          0.0, 10)))               # a forged result
                spy.send(codec.tcu_heartbeat(0, STATE_RUNNING, k + 1000))          # a forged heartbeat
                break
        assert k is not None, f"the run never reached step {at_step}"
        out, err = proc.communicate(timeout=300)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        spy.shutdown()
        remove_channel(channel)
    assert proc.returncode == 0, err
    s, ref = json.loads(out), json.loads(clean)
    print(s["rejected_frames"], s["tcu_rejected_frames"], s["suspicious"])
    assert s["frame_auth"] == "on" and ref["frame_auth"] == "on"
    # every node sees every frame: the plant and the TCU each reject the two copies and the three forgeries
    assert s["rejected_frames"] == {"replayed": 2, "forged": 3}
    assert s["tcu_rejected_frames"] == {"replayed": 2, "forged": 3}
    assert not s["suspicious"]
    for key in ("identified", "t_identified_s", "corrections", "params", "samples", "r2", "peak_mu_err_percent"):
        assert s[key] == ref[key], key


def test_in_process_frames_are_not_authenticated_unless_asked(tmp_path):
    """``auth = "auto"`` is off in process (no other node can put a frame there): zero trailers in the
    log; ``on`` still authenticates them (MAC trailers), and the run identifies the same."""
    from mcap.reader import make_reader

    from hil.log.schemas import TOPICS, TYPES

    def trailers(summary):
        cls = TYPES[TOPICS["/can/frames"]]
        with open(summary["mcap"], "rb") as f:
            rows = [cls.FromString(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/can/frames"])]
        return {bytes(r.data[-8:]) for r in rows if r.arbitration_id in (SENSOR_ID, COMMAND_ID)}

    runs = {}
    for mode in ("auto", "on"):
        args = ["run", str(ROOT / "scenarios" / "ffcc_a.toml"), "--bus", "inprocess", "--no-rrd",
                "--out", str(tmp_path / mode), "--set", f"bus.auth=\"{mode}\"", "--json"]
        r = subprocess.run(hil_command() + args, capture_output=True, text=True, env=subprocess_env(), timeout=300)
        assert r.returncode == 0, r.stderr
        runs[mode] = json.loads(r.stdout)
    assert runs["auto"]["frame_auth"] == "off" and trailers(runs["auto"]) == {bytes(8)}
    assert runs["on"]["frame_auth"] == "on" and len(trailers(runs["on"])) > 1000
    assert runs["auto"]["params"] == runs["on"]["params"] and runs["auto"]["identified"]
