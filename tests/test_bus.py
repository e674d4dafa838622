"""HIL over a real bus between two processes: the python-can-remote hub here (vcan tests: test_vcan.py).

Every run is ``hil run`` as a user runs it; the TCU is its own process.  Helpers at the top are
shared with test_vcan.py.
"""
import json
import math
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import can
import pytest
from mcap.reader import make_reader

from hil.testing import alive, children_of, cmdline  # noqa: F401 (alive: other tests import it here)
from hil.bus.link import Hub, open_bus
from hil.bus.frames import TCU_HEARTBEAT_ID, WALL_CLOCK_IDS, FrameCodec, load_dbc
from hil.log.read import read_log
from identifier.messages import SensorReading

from .conftest import ROOT, hil, hil_command, once_per_session, subprocess_env

HEARTBEATS = WALL_CLOCK_IDS          # heartbeats and the TCU's TcuScenario: sent by the wall clock
#: where each frame's authentication trailer starts, from the DBC
TRAILER_AT = {m.frame_id: m.get_signal_by_name("AuthFreshness").start // 8 for m in load_dbc().messages}
IDENT_KEYS = ("identified", "t_identified_s", "t_detected_s", "t_serious_s", "corrections", "params", "samples",
              "mse", "rmse", "mae", "r2", "peak_mu_err_percent", "peak_creep_err_percent", "observer_lag_ms")


# -- helpers (also used by test_vcan.py) ------------------------------------------------------------
def hil_run(args, timeout=600, check=True):
    r = hil("run", *args, timeout=timeout, cwd=ROOT)
    if check:
        assert r.returncode == 0, r.stderr
    return r


def run_json(scenario_args, bus, out, *extra, timeout=600):
    r = hil_run([*scenario_args, "--bus", bus, "--out", str(out), "--json", *extra], timeout=timeout)
    return json.loads(r.stdout), r.stderr


def data_streams(mcap_path):
    """(tx, rx): the (id, payload) of every valid non-heartbeat frame the plant sent / received, in order,
    the authentication trailer zeroed (its MAC is of a key made for each run, hil/bus/secoc.py)."""
    frames = read_log(mcap_path, {"/can/frames"}).topic("/can/frames")

    def payload(f):
        at = TRAILER_AT[f.arbitration_id]
        return bytes(f.data[:at]) + bytes(8) + bytes(f.data[at + 8:])

    tx = [(f.arbitration_id, payload(f)) for f in frames if f.direction == "tx" and f.arbitration_id not in HEARTBEATS]
    rx = [(f.arbitration_id, payload(f)) for f in frames
          if f.direction == "rx" and f.status == "ok" and f.arbitration_id not in HEARTBEATS]
    return tx, rx


def identification(summary):
    return {k: summary[k] for k in IDENT_KEYS}


def wait_for(pred, timeout, what):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


FFCC_A = ["scenarios/ffcc_a.toml", "--seed", "1"]


@pytest.fixture(scope="module")
def inprocess_run(tmp_path_factory):
    """(hil run --json summary, log) of ffcc_a on the in-process bus, made once per test session."""
    def make(out):
        s, _ = run_json(FFCC_A, "inprocess", out)
        return s, str(out / "ffcc_a-gp-1.mcap")

    s, path = once_per_session(tmp_path_factory, "bus_inprocess_run", make)
    return s, Path(path)


@pytest.fixture(scope="module")
def hub_run(tmp_path_factory):
    """(hil run --json summary, log, stderr) of ffcc_a over the hub, made once per test session."""
    def make(out):
        s, err = run_json(FFCC_A, "hub", out)
        return s, str(out / "ffcc_a-gp-1.mcap"), err

    s, path, err = once_per_session(tmp_path_factory, "bus_hub_run", make)
    return s, Path(path), err


# -- the bus factory ------------------------------------------------------------------------------
def test_unknown_bus_is_one_clear_line():
    r = hil_run(["scenarios/ffcc_a.toml", "--bus", "nonsense"], check=False)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "nonsense" in lines[0] and "available here: auto, local, hub, inprocess" in lines[0]


def test_unavailable_socketcan_channel_names_it_and_why():
    r = hil_run(["scenarios/ffcc_a.toml", "--bus", "socketcan:nocan7"], check=False)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "socketcan:nocan7" in lines[0] and "available here" in lines[0]
    assert "no SocketCAN" in lines[0] or "no CAN interface 'nocan7'" in lines[0]


def test_hub_listens_on_localhost_relays_fd_frames_and_stops():
    handle = open_bus("hub")
    port = handle.hub.port
    pid = handle.hub.proc.pid
    try:
        assert handle.peer_spec == f"remote:ws://127.0.0.1:{port}/"
        peer = open_bus(handle.peer_spec)
        try:
            msg = can.Message(arbitration_id=0x100, data=bytes(range(24)), is_fd=True, bitrate_switch=True,
                              is_extended_id=False)
            handle.bus.send(msg)
            got = peer.bus.recv(5)
            assert got is not None and bytes(got.data) == bytes(range(24)) and got.is_fd and got.bitrate_switch
            assert handle.bus.recv(0.2) is None           # no echo of its own frames
        finally:
            peer.close()
    finally:
        handle.close()
    assert not alive(pid)
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=0.5)


def test_the_hub_serves_no_files():
    """python-can-remote 0.3.0 answers any non-websocket GET with a file below its package directory,
    ``..`` included (it returned /etc/passwd); the hub ``hil`` starts answers 404 to every one, and
    still relays frames."""
    import urllib.error
    import urllib.request
    handle = open_bus("hub")
    try:
        base = f"http://127.0.0.1:{handle.hub.port}"
        for path in ("/", "/index.html", "/../../../../../../../../etc/passwd", "/..%2f..%2f..%2fetc/passwd"):
            req = urllib.request.Request(base + path)
            req.selector = path                      # sent as written, not normalised by urllib
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(req, timeout=5)
            assert e.value.code == 404, path
        peer = open_bus(handle.peer_spec)
        try:
            handle.bus.send(can.Message(arbitration_id=0x100, data=bytes(32), is_fd=True, is_extended_id=False))
            got = peer.bus.recv(5)
            assert got is not None and bytes(got.data) == bytes(32)
        finally:
            peer.close()
    finally:
        handle.close()


# -- the same run over two transports ------------------------------------------------------------
def test_inprocess_and_hub_give_identical_frames_and_identification(inprocess_run, hub_run):
    s_in, path_in = inprocess_run
    s_hub, path_hub, _ = hub_run
    assert s_in["bus"] == "inprocess" and s_hub["bus"] == "hub"
    assert s_in["identified"]
    assert identification(s_hub) == identification(s_in)
    tx_in, rx_in = data_streams(path_in)
    tx_hub, rx_hub = data_streams(path_hub)
    assert len(tx_in) == 2000 and len(rx_in) >= 2000       # DriverDemand and PlantSensor each period of 1 s
    assert tx_hub == tx_in and rx_hub == rx_in


@pytest.mark.parametrize("spin_s", ["0", "0.002"])
def test_local_lockstep_polling_or_sleeping_gives_the_inprocess_frames(tmp_path, inprocess_run, spin_s):
    """[bus] lockstep_spin_s decides only how each node waits for the other: polled or asleep in
    the bus, the local run's frames and identification are the in-process run's."""
    s_in, path_in = inprocess_run
    s, _ = run_json(FFCC_A, "local", tmp_path, "--set", f"bus.lockstep_spin_s={spin_s}")
    assert s["bus"].startswith("local") and s["identified"]
    assert identification(s) == identification(s_in)
    assert data_streams(tmp_path / "ffcc_a-gp-1.mcap") == data_streams(path_in)


def test_udp_multicast_lockstep_gives_the_inprocess_frames(tmp_path, inprocess_run):
    """python-can's udp_multicast bus on lo (hil/bus/multicast.py), a group drawn for the run and handed to
    the built-in TCU process: the frames and identification of the in-process run, nothing rejected."""
    s_in, path_in = inprocess_run
    s, err = run_json(FFCC_A, "udp_multicast", tmp_path)
    assert s["bus"] == "udp_multicast" and s["frame_auth"] == "off" and s["rejected_frames"] == {}, s
    assert "warning: bus udp_multicast: any process of any user on this machine can join it (239.255." in err, err
    assert identification(s) == identification(s_in)
    assert data_streams(tmp_path / "ffcc_a-gp-1.mcap") == data_streams(path_in)


def test_a_negative_lockstep_spin_is_refused_by_name():
    r = hil_run(["scenarios/ffcc_a.toml", "--bus", "inprocess", "--set", "bus.lockstep_spin_s=-0.001"], check=False)
    assert r.returncode == 2 and "[bus] lockstep_spin_s" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_frames_change_nothing_against_the_identifier_fed_directly(inprocess_run):
    """The same sensor readings fed straight into a TractionIdentifier, no frames, no bus (as the
    bench does): the frames' doubles add no quantisation, so the identification is the same."""
    from identifier import DEFAULT_STRATEGY
    from hil.benchmarks.identify import generate, replay
    from hil.config import load_scenario

    direct, _ = replay(generate(load_scenario(ROOT / "scenarios/ffcc_a.toml"), 1), DEFAULT_STRATEGY, None)
    s, _ = inprocess_run
    keys = [k for k in IDENT_KEYS if k != "observer_lag_ms"]     # the bench keeps no observer trace
    assert {k: s[k] for k in keys} == {k: direct[k] for k in keys}


def test_json_keys_and_mcap_holds_every_frame_raw(hub_run):
    s, path, err = hub_run
    for key in ("scenario", "strategy", "seed", "bus", "identified", "t_fault_s", "t_serious_s", "t_identified_s",
                "rt_percent", "params", "mse", "rmse", "mae", "r2", "peak_mu_err_percent", "peak_creep_err_percent",
                "corrections", "mcap", "observer_lag_ms", "mode", "wall_s", "sim_s"):
        assert key in s, key
    assert s["mode"] == "lockstep" and s["sim_s"] == pytest.approx(1.0) and s["wall_s"] > 0
    assert "bus load" in err and "%" in err
    log = read_log(path)
    assert log.complete
    frames = log.topic("/can/frames")
    assert sum(f.direction == "tx" for f in frames) == s["frames_tx"]
    assert sum(f.direction == "rx" for f in frames) == s["frames_rx"]
    assert all(f.wall_time_ns > 0 and f.send_time_ns > 0 and f.is_fd for f in frames)
    # a replay can decode from the raw frames alone: they give the decoded topics back
    db = load_dbc()
    sensor = [db.decode_message(f.arbitration_id, f.data) for f in frames if f.arbitration_id == 0x100]
    assert [d["MotorSpeed"] for d in sensor] == [m.motor_speed_rad_s for m in log.topic("/plant/sensor")]
    status = [db.decode_message(f.arbitration_id, f.data) for f in frames
              if f.arbitration_id == 0x120 and f.direction == "rx"]
    observer = log.topic("/tcu/observer")
    assert [d["MuHat"] for d in status if d["ObserverValid"]] == [m.mu_hat for m in observer]
    assert len(observer) == 1000
    assert "hil.dbc" in log.metadata["dbc"]["name"] and "BO_ 256 PlantSensor" in log.metadata["dbc"]["text"]


def test_garbage_on_the_hub_is_counted_on_both_sides_and_changes_nothing(tmp_path, inprocess_run):
    """A third node floods the bus with malformed frames during a lockstep run."""
    hub = Hub()
    url = f"remote:ws://127.0.0.1:{hub.port}/"
    proc = None
    try:
        spy = open_bus(url)
        proc = subprocess.Popen(hil_command() + ["run", *FFCC_A, "--bus", url, "--out", str(tmp_path), "--json"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(),
                                cwd=ROOT)
        # wait for the first sensor frame: both nodes are up from then on
        end = time.monotonic() + 60
        while True:
            m = spy.bus.recv(0.5)
            if m is not None and m.arbitration_id == 0x100:
                break
            assert time.monotonic() < end and proc.poll() is None, "the run never started"
        nan = math.nan
        import struct
        garbage = [
            can.Message(arbitration_id=0x123, data=b"\xde\xad\xbe\xef", is_extended_id=False),
            can.Message(arbitration_id=0x1FFFFFFF, data=b"\x00", is_extended_id=True),
            can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=False),
            can.Message(arbitration_id=0x100, data=struct.pack("<Idd", 3, nan, 10.0) + bytes(12), is_fd=True,
                        is_extended_id=False),
            can.Message(arbitration_id=0x100, data=struct.pack("<Idd", 3, 60.0, math.inf) + bytes(12), is_fd=True,
                        is_extended_id=False),
            can.Message(arbitration_id=0x110, data=struct.pack("<Id", 3, 1e12) + bytes(8), is_fd=True,
                        is_extended_id=False),
            can.Message(arbitration_id=0x702, data=bytes(3), is_extended_id=False),
        ]
        sent = 0
        for _ in range(10):
            for g in garbage:
                spy.bus.send(g)
                sent += 1
        out, err = proc.communicate(timeout=600)
        spy.close()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        hub.stop()
    assert proc.returncode == 0, err
    s = json.loads(out)
    assert sum(s["rejected_frames"].values()) == sent
    assert sum(s["tcu_rejected_frames"].values()) == sent
    assert s["rejected_frames"]["non_finite:MotorSpeed"] == 10 and s["tcu_rejected_frames"]["bad_length"] == 20
    assert s["tcu_rejected_readings"] == 0
    ref, ref_path = inprocess_run
    assert identification(s) == identification(ref)
    assert data_streams(tmp_path / "ffcc_a-gp-1.mcap") == data_streams(ref_path)
    rejected = [f for f in read_log(tmp_path / "ffcc_a-gp-1.mcap", {"/can/frames"}).topic("/can/frames")
                if f.status not in ("ok", "late")]
    assert len(rejected) == sent


# -- faults and stopping ---------------------------------------------------------------------------
def _start_long_run(tmp_path, *extra):
    cmd = hil_command() + ["run", "scenarios/ffcc_a.toml", "--bus", "hub", "--out", str(tmp_path),
                           "--set", "run.duration_s=60", "--set", "run.fault_time_s=55", *extra]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(),
                            cwd=ROOT)
    path = tmp_path / "ffcc_a-gp-1.mcap"
    wait_for(lambda: path.exists() and path.stat().st_size > 60_000 or proc.poll() is not None, 120, "the run")
    assert proc.poll() is None, proc.communicate()[1]
    return proc, path


def test_silent_tcu_is_a_recorded_fault_and_exit_3(tmp_path):
    proc, path = _start_long_run(tmp_path)
    tcu = [p for p in children_of(proc.pid) if "hil.tcu_node" in cmdline(p)]
    assert len(tcu) == 1
    try:
        os.kill(tcu[0], signal.SIGSTOP)
        t0 = time.monotonic()
        out, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
    finally:
        if alive(tcu[0]):
            os.kill(tcu[0], signal.SIGKILL)
    assert proc.returncode == 3
    assert "TCU silent" in err and "fault recorded" in err and "Traceback" not in err
    assert took < 10
    with open(path, "rb") as f:                       # a finished MCAP (footer and summary section)
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert "TCU silent" in meta["fault"]["reason"]
    events = read_log(path, {"/run/events"}).topic("/run/events")
    assert any(e.level == "ERROR" and "TCU silent" in e.text for e in events)


def test_a_tcu_that_dies_mid_run_is_exit_3_and_json_still_prints_one_object(tmp_path):
    proc, path = _start_long_run(tmp_path, "--json")
    tcu = [p for p in children_of(proc.pid) if "hil.tcu_node" in cmdline(p)]
    assert len(tcu) == 1
    os.kill(tcu[0], signal.SIGKILL)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 3, err
    assert "the TCU process was killed by SIGKILL" in err and "(a crash)" in err and "Traceback" not in err
    s = json.loads(out)                               # exactly one JSON object, with the fault in it
    assert "TCU process was killed by SIGKILL" in s["fault"] and s["mcap"] == str(path) and s["identified"] is False
    assert s["wall_s"] > 0 and s["sim_s_per_wall_s"] > 0          # up to the fault
    with open(path, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert "TCU process was killed by SIGKILL" in meta["fault"]["reason"]


def test_ctrl_c_stops_plant_tcu_and_hub_and_closes_the_mcap(tmp_path):
    proc, path = _start_long_run(tmp_path)
    kids = children_of(proc.pid)
    assert len(kids) == 2                            # the hub and the TCU
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err
    assert "not properly shut down" not in err and "Exception ignored" not in err, err
    wait_for(lambda: not any(alive(k) for k in kids), 10, "the hub and TCU to end")
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 1000
    events = read_log(path, {"/run/events"}).topic("/run/events")
    assert any("interrupted" in e.text for e in events)


def test_sigterm_ends_a_run_like_ctrl_c(tmp_path):
    proc, path = _start_long_run(tmp_path)
    kids = children_of(proc.pid)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    assert proc.returncode == 130
    wait_for(lambda: not any(alive(k) for k in kids), 10, "the hub and TCU to end")
    with open(path, "rb") as f:
        assert make_reader(f).get_summary() is not None


def test_a_killed_plant_leaves_no_hub_or_tcu_behind(tmp_path):
    proc, path = _start_long_run(tmp_path)
    kids = children_of(proc.pid)
    assert len(kids) == 2
    proc.kill()
    proc.communicate(timeout=30)
    wait_for(lambda: not any(alive(k) for k in kids), 10, "the hub and TCU to end")


def test_silent_plant_ends_a_standalone_tcu(tmp_path):
    hub = Hub()
    url = f"remote:ws://127.0.0.1:{hub.port}/"
    proc = None
    try:
        plant = open_bus(url)
        proc = subprocess.Popen(hil_command() + ["tcu", "scenarios/ffcc_a.toml", "--bus", url, "--json"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(),
                                cwd=ROOT)
        codec = FrameCodec(1e-3)
        end = time.monotonic() + 60
        while True:                                  # the TCU says it is there
            m = plant.bus.recv(0.5)
            if m is not None and m.arbitration_id == TCU_HEARTBEAT_ID:
                break
            assert time.monotonic() < end and proc.poll() is None, "the TCU never started"
        commands = 0
        for k in range(20):
            plant.bus.send(codec.sensor(SensorReading(k, 63.7, 10.0)))
            while True:
                m = plant.bus.recv(5)
                assert m is not None
                if m.arbitration_id == 0x110:
                    commands += 1
                    break
        t0 = time.monotonic()
        out, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
        plant.close()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        hub.stop()
    assert commands == 20
    assert proc.returncode == 3 and "plant silent" in err and "Traceback" not in err
    assert took < 10
    report = json.loads(out)
    assert report["sensor_frames"] == 20 and report["last_step"] == 19


def test_plant_and_tcu_started_separately(tmp_path, inprocess_run):
    """``hil tcu`` on a bus, ``hil run --tcu external`` on the same bus: as a rig with its own TCU."""
    hub = Hub()
    url = f"remote:ws://127.0.0.1:{hub.port}/"
    tcu = None
    try:
        tcu = subprocess.Popen(hil_command() + ["tcu", *FFCC_A, "--bus", url, "--json"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=ROOT)
        s, _ = run_json(FFCC_A, url, tmp_path, "--tcu", "external")
        out, err = tcu.communicate(timeout=60)
    finally:
        if tcu is not None and tcu.poll() is None:
            tcu.kill()
        hub.stop()
    assert tcu.returncode == 0, err
    ref, ref_path = inprocess_run
    for key in ("identified", "t_identified_s", "corrections", "params", "t_serious_s"):
        assert s[key] == ref[key], key
    # the samples travel in TcuSample frames: the external TCU's run has the same fit metrics
    for key in ("samples", "mse", "rmse", "mae", "r2", "t_detected_s", "observer_lag_ms"):
        assert s[key] == ref[key], key
    assert s["tcu_rejected_frames"] is None          # only the TCU knows its counters; it prints them:
    report = json.loads(out)
    assert report["samples"] == ref["samples"] and report["plant_state"] == "finished" and report["exit"] == 0
    assert data_streams(tmp_path / "ffcc_a-external-1.mcap") == data_streams(ref_path)   # external: named so


def test_standalone_tcu_needs_a_shared_bus():
    r = subprocess.run(hil_command() + ["tcu", "scenarios/ffcc_a.toml", "--bus", "inprocess"], capture_output=True,
                       text=True, env=subprocess_env(), cwd=ROOT, timeout=60)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "inprocess" in r.stderr


# -- real time and bus load ------------------------------------------------------------------------
@pytest.mark.realtime
def test_realtime_over_the_hub_records_timing(tmp_path):
    s, err = run_json(["scenarios/ffcc_a.toml", "--set", "run.duration_s=0.4", "--set", "run.fault_time_s=0.3",
                       "--set", "bus.silence_periods=100", "--set", "bus.max_missed_fraction=1"], "hub", tmp_path,
                      "--mode", "realtime")
    assert s["mode"] == "realtime" and s["sim_s"] == pytest.approx(0.4)
    assert isinstance(s["missed_deadlines"], int) and 0 <= s["missed_deadlines"] <= 400
    assert s["jitter_p99_us"] >= 0 and s["wall_s"] >= 0.39      # paced by the wall clock
    timing = read_log(tmp_path / "ffcc_a-gp-1.mcap", {"/loop/timing"}).topic("/loop/timing")
    assert [t.step for t in timing] == list(range(400))
    assert sum(t.missed_deadline for t in timing) == s["missed_deadlines"]
    print(f"\nrealtime 0.4 s over the hub: missed {s['missed_deadlines']}, jitter p99 {s['jitter_p99_us']:.0f} us, "
          f"round trip p50 {s['round_trip_p50_us']:.0f} us")


def test_bus_load_above_70_percent_warns(tmp_path):
    short = ["scenarios/ffcc_a.toml", "--set", "run.duration_s=0.02", "--set", "run.fault_time_s=0.01"]
    _, err = run_json(short + ["--set", "bus.bitrate=250000", "--set", "bus.data_bitrate=1000000"], "inprocess",
                      tmp_path)
    assert "warning: bus load" in err and "above 70 %" in err
    _, err = run_json(short, "inprocess", tmp_path / "quiet")
    assert "bus load" in err and "warning" not in err
    _, err = run_json(short, "inprocess", tmp_path / "quiet")       # the same log name again: said, not silent
    assert "warning: replacing" in err and "ffcc_a-gp-1.mcap" in err


def test_bad_bus_table_names_the_field(tmp_path):
    r = hil_run(["scenarios/ffcc_a.toml", "--bus", "inprocess", "--set", "bus.bitrate=-5"], check=False)
    assert r.returncode == 2 and "[bus] bitrate" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_run_that_fails_before_logging_keeps_the_old_log_and_does_not_say_replacing(tmp_path):
    """The log of an earlier run stays as it was when a later run with the same name fails at the bus, and
    the warning that it is being replaced comes only when it is."""
    old = tmp_path / "ffcc_a-gp-1.mcap"
    old.write_bytes(b"an earlier run's log")
    r = hil_run(["scenarios/ffcc_a.toml", "--bus", "socketcan:nocan7", "--out", str(tmp_path)], check=False)
    assert r.returncode == 2 and "replacing" not in r.stderr, r.stderr
    assert old.read_bytes() == b"an earlier run's log"
