"""The HIL on real SocketCAN vcan0, with can-utils as a real third node on the bus.

Run with ``tests/uml/run_vcan_tests.sh`` (natively where the kernel has vcan0, otherwise inside
User-Mode Linux).  Under CI=true these tests fail instead of skipping when vcan0 or can-utils are
missing; elsewhere the skip says exactly why.
"""
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import time

import pytest

from hil.bus.link import open_bus, vcan_available
from hil.bus.frames import load_dbc
from hil.log.read import read_log

from .conftest import ROOT, hil_command, subprocess_env
from .test_bus import FFCC_A, data_streams, identification, run_json

pytestmark = pytest.mark.vcan


@pytest.fixture(scope="module", autouse=True)
def vcan0():
    ok, why = vcan_available("vcan0")
    missing = [t for t in ("candump", "cansend") if shutil.which(t) is None]
    if ok and not missing:
        return
    reason = (f"needs SocketCAN vcan0 ({why})" if not ok else f"needs can-utils ({', '.join(missing)} not found)") \
        + "; tests/uml/run_vcan_tests.sh runs these inside User-Mode Linux"
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI=true: the vcan tests must run, but this machine {reason}")
    pytest.skip(reason)


def parse_candump(text):
    """``candump -L`` lines -> [(id, extended, fd, remote, data)]."""
    out = []
    for line in text.splitlines():
        parts = line.split()
        if len(parts) != 3:
            continue
        frame = parts[2]
        if "##" in frame:
            ident, rest = frame.split("##", 1)
            data, fd = bytes.fromhex(rest[1:]), True
        else:
            ident, rest = frame.split("#", 1)
            fd = False
            data = b"" if rest.startswith("R") else bytes.fromhex(rest)
        out.append((int(ident, 16), len(ident) == 8, fd, rest.startswith("R"), data))
    return out


def test_candump_records_the_run_and_the_dbc_decodes_it_to_the_mcap_values(tmp_path):
    # candump writes to a file: a pipe nobody reads would block it and the socket would drop frames
    with open(tmp_path / "candump.log", "w") as f:
        dump = subprocess.Popen(["candump", "-L", "vcan0"], stdout=f)
        try:
            time.sleep(0.3)
            s, _ = run_json(FFCC_A, "socketcan:vcan0", tmp_path)
            time.sleep(0.3)
        finally:
            dump.send_signal(signal.SIGINT)
            dump.wait(timeout=10)
    dumped = parse_candump((tmp_path / "candump.log").read_text())
    log = read_log(tmp_path / "ffcc_a-gp-1.mcap")
    frames = log.topic("/can/frames")
    # every frame the plant sent or received is on the wire, and nothing else is (per id, in order)
    by_id_mcap, by_id_dump = {}, {}
    for f in frames:
        by_id_mcap.setdefault(f.arbitration_id, []).append(f.data)
    for ident, ext, fd, remote, data in dumped:
        assert fd and not ext and not remote
        by_id_dump.setdefault(ident, []).append(data)
    for ident in sorted(set(by_id_dump) | set(by_id_mcap)):
        a, b = by_id_dump.get(ident, []), by_id_mcap.get(ident, [])
        first = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), None)
        assert a == b, f"id 0x{ident:X}: candump {len(a)} frames, MCAP {len(b)}, first difference at {first}"
    assert len(by_id_dump[0x100]) == 1000 and len(by_id_dump[0x110]) == 1000
    # the DBC decodes the wire frames to the values the MCAP holds
    db = load_dbc()
    sensors = [db.decode_message(0x100, d) for d in by_id_dump[0x100]]
    recorded = log.topic("/plant/sensor")
    assert [d["MotorSpeed"] for d in sensors] == [m.motor_speed_rad_s for m in recorded]
    assert [d["TrainSpeed"] for d in sensors] == [m.train_speed_ms for m in recorded]
    assert [d["SensorStep"] for d in sensors] == [m.step for m in recorded]
    status = [db.decode_message(0x120, d) for d in by_id_dump[0x120]]
    observer = log.topic("/tcu/observer")
    assert [d["MuHat"] for d in status if d["ObserverValid"]] == [m.mu_hat for m in observer]
    assert [d["CreepSpeed"] for d in status if d["ObserverValid"]] == [m.creep_speed_kmh for m in observer]
    results = [db.decode_message(0x130, d, decode_choices=False) for d in by_id_dump[0x130]]
    events = log.topic("/tcu/identification")
    assert len(results) == len(events) > 0
    assert [[r[f"Param{i}"] for i in range(r["ParamCount"])] for r in results] == [list(e.params) for e in events]
    assert sum(r["ResultKind"] == 0 for r in results) == s["corrections"]


def _fd_hex(data: bytes) -> str:
    return data.hex().upper()


GARBAGE = [
    "123#DEADBEEF",                                                          # unknown id
    "1FFFFFFF#00",                                                           # extended id
    "100#0011223344556677",                                                  # sensor id, classic 8 bytes
    # (+ a zero authentication trailer: frames are not authenticated on SocketCAN by default)
    "100##1" + _fd_hex(struct.pack("<Idd", 7, math.nan, 10.0) + bytes(12)),  # NaN motor speed
    "100##1" + _fd_hex(struct.pack("<Idd", 7, 60.0, math.inf) + bytes(12)),  # inf train speed
    "100##1" + _fd_hex(struct.pack("<Idd", 7, 1e7, 10.0) + bytes(12)),       # out of range
    "110##1" + _fd_hex(struct.pack("<Id", 7, 1e12) + bytes(8)),              # torque out of range
    "120##1" + _fd_hex(struct.pack("<IBBHddd", 7, 9, 1, 0, 0.1, 1.0, 0.0) + bytes(16)),  # stage 9
    "701#R",                                                                 # remote frame
    "702##1" + "00" * 12,                                                    # heartbeat, wrong length
]


def _message(frame: str):
    """A python-can message from cansend's syntax (``ID#DATA``, ``ID##FLAGS DATA`` for CAN FD, ``ID#R``)."""
    import can

    ident, rest = frame.split("#", 1)
    extended = len(ident) == 8
    if rest.startswith("#"):
        return can.Message(arbitration_id=int(ident, 16), is_extended_id=extended, is_fd=True,
                           bitrate_switch=bool(int(rest[1], 16) & 1), data=bytes.fromhex(rest[2:]))
    if rest.startswith("R"):
        return can.Message(arbitration_id=int(ident, 16), is_extended_id=extended, is_remote_frame=True)
    return can.Message(arbitration_id=int(ident, 16), is_extended_id=extended, data=bytes.fromhex(rest))


def test_vcan_carries_the_inprocess_frames_with_garbage_from_third_nodes_counted(tmp_path):
    """A run on vcan0 (picked by ``auto``) sends and accepts exactly the frames of the same run on the
    in-process bus and identifies the same, while third nodes put garbage on vcan0: can-utils' cansend one
    frame, a python-can socket of this process the others (a cansend process start takes seconds in the
    guest).  Each garbage frame is counted by reason on both sides and logged.  (The hub's equality with the
    in-process bus is tests/test_bus.py's, on the host, where a run costs less than in the guest.)"""
    # a 3 s run (fault at 2.5 s): the garbage is all sent within the first second of simulated time
    args = [*FFCC_A, "--set", "run.duration_s=3.0", "--set", "run.fault_time_s=2.5"]
    ref, _ = run_json(args, "inprocess", tmp_path / "ref")
    watch = open_bus("socketcan:vcan0")
    proc = subprocess.Popen(hil_command() + ["run", *args, "--bus", "auto", "--out", str(tmp_path), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=ROOT)
    try:
        end = time.monotonic() + 120
        while True:                 # the first sensor frame: plant and TCU are both on the bus
            m = watch.bus.recv(0.5)
            if m is not None and m.arbitration_id == 0x100:
                break
            assert time.monotonic() < end and proc.poll() is None, "the run never started"
        sent = 0
        for frame in GARBAGE[:-1]:
            watch.bus.send(_message(frame))
            sent += 1
        subprocess.run(["cansend", "vcan0", GARBAGE[-1]], check=True, timeout=30)
        sent += 1
        still_running = proc.poll() is None
        out, err = proc.communicate(timeout=600)
    finally:
        watch.close()
        if proc.poll() is None:
            proc.kill()
    assert still_running, f"the run ended before all garbage was sent: the test proves nothing (exit {proc.returncode}, sent {sent}): {err[-800:]}"
    assert proc.returncode == 0, err
    s = json.loads(out)
    assert s["bus"] == "socketcan:vcan0"           # auto picks vcan0 where the kernel has it
    assert s["identified"] and ref["identified"]
    assert identification(s) == identification(ref)
    streams = data_streams(tmp_path / "ref" / "ffcc_a-gp-1.mcap")
    assert len(streams[0]) == 6000          # DriverDemand and PlantSensor each period of 3 s
    assert data_streams(tmp_path / "ffcc_a-gp-1.mcap") == streams
    assert sum(s["rejected_frames"].values()) == sent == len(GARBAGE)
    assert sum(s["tcu_rejected_frames"].values()) == sent
    assert s["tcu_rejected_readings"] == 0
    assert s["rejected_frames"]["non_finite:MotorSpeed"] == 1 and s["rejected_frames"]["remote_frame"] == 1
    rejected = [f for f in read_log(tmp_path / "ffcc_a-gp-1.mcap", {"/can/frames"}).topic("/can/frames")
                if f.status not in ("ok", "late")]
    assert len(rejected) == sent
    print(f"\ngarbage: {sent} frames sent, plant counted {sum(s['rejected_frames'].values())}, "
          f"TCU counted {sum(s['tcu_rejected_frames'].values())}; lockstep sim s per wall s: "
          f"inprocess {ref['sim_s'] / ref['wall_s']:.2f}, vcan0 {s['sim_s'] / s['wall_s']:.2f}")


def test_gap_reads_candump_l_of_a_run_like_its_mcap(tmp_path):
    """Issue 18 item 7: ``candump -l`` (can-utils' own log format) of a run on vcan0 with a hidden
    load transfer; the reader ``hil gap`` uses gives the same readings, commands, TCU outputs and events
    from that file as from the run's MCAP, hence the same diagnosis (a diagnosis is a function of them; tests/test_gap.py diagnoses a CAN log
    beside its MCAP twin on the host, where a diagnosis costs a fraction of what it costs the guest)."""
    import numpy as np

    from hil.gap.data import read_real_log
    from hil.config import load_scenario

    dump = subprocess.Popen(["candump", "-l", "vcan0"], cwd=tmp_path, stdout=subprocess.DEVNULL)
    try:
        time.sleep(0.3)
        run_json(FFCC_A, "socketcan:vcan0", tmp_path, "--reality", "load_transfer:bogie_height_m=1.5")
        time.sleep(0.3)
    finally:
        dump.send_signal(signal.SIGINT)
        dump.wait(timeout=10)
    logs = sorted(tmp_path.glob("candump-*.log"))
    assert len(logs) == 1, logs
    period_s = load_scenario(ROOT / "scenarios" / "ffcc_a.toml").run.exchange_period_s
    dumped = read_real_log(logs[0], period_s)
    mcap = read_real_log(next(tmp_path.glob("*.mcap")))
    print(dumped.source, dumped.n, mcap.n)
    assert dumped.source["format"] == "can-log" and dumped.source["damage"] == ""
    assert dumped.n == mcap.n > 0
    for name in ("step", "motor_speed_rad_s", "train_speed_ms", "torque_cmd_nm", "tcu_creep_kmh", "tcu_mu_hat"):
        np.testing.assert_allclose(getattr(dumped, name), getattr(mcap, name), rtol=1e-6, err_msg=name)
    assert len(dumped.identification) == len(mcap.identification) >= 1


def test_the_example_suite_passes_on_vcan0_in_lockstep(tmp_path):
    """Issue 37 item 8: the example suite of the built-in TCU (scenarios/suites/test_ffcc_a.*) in a real pytest
    session on vcan0, the built-in TCU as a second process: every test passes, the JUnit XML validates
    against junit-10.xsd.  (test_their_tcu.toml judges round trips of a TCU on its own DBC, which a guest
    under User-Mode Linux cannot meet: tests/test_mapping.py runs it on the host.)"""
    import sys

    from lxml import etree

    junit = tmp_path / "junit.xml"
    suite = [str(ROOT / "scenarios" / "suites" / f"test_ffcc_a.{ext}") for ext in ("py", "toml")]
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "-q",
                        *suite, "--hil-bus", "socketcan:vcan0", "--hil-mode", "lockstep",
                        "--hil-out", str(tmp_path / "out"), "--junitxml", str(junit)],
                       cwd=tmp_path, env=subprocess_env(CI="true"), capture_output=True, text=True, timeout=900)
    assert r.returncode == 0 and "7 passed" in r.stdout, r.stdout[-3000:] + r.stderr[-3000:]
    schema = etree.XMLSchema(etree.parse(str(ROOT / "tests" / "data" / "junit-10.xsd")))
    assert schema.validate(etree.parse(str(junit))), schema.error_log
    props = {p.get("name"): p.get("value") for p in etree.parse(str(junit)).iter("property")}
    assert props["bus"] == "socketcan:vcan0 lockstep"


def test_the_python_can_example_tcu_controls_the_wheel_on_vcan0(tmp_path):
    """Issue 49 item 2 on SocketCAN: the docs' example TCU (docs/examples/python_can_tcu.py: python-can and
    cantools, no import of this project; run here by this tree's Python, ``-I``, without PYTHONPATH) on vcan0
    against ``hil run --tcu external`` in lockstep on the example suite's scenario and overrides, judged by
    ``hil check``: no macro-slip, the wet patch's adhesion used, a command every period.  (TIM-1, a round
    trip in wall time, is the host's: tests/test_python_can_tcu.py; a guest under User-Mode Linux is slower.)
    The virtualenv without this project is tests/test_python_can_tcu.py's too: the guest has no registry."""
    import sys
    import tomllib

    suite_path = ROOT / "scenarios" / "suites" / "test_their_tcu.toml"
    suite = tomllib.loads(suite_path.read_text())
    sets = [a for k, v in suite["set"].items() for a in ("--set", f"{k}={json.dumps(v)}")]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    with open(tmp_path / "tcu.log", "w") as log:
        tcu = subprocess.Popen([sys.executable, "-I", str(ROOT / "docs" / "examples" / "python_can_tcu.py"), "--dbc",
                                str(ROOT / "scenarios" / "suites" / "their.dbc"), "--bus", "socketcan:vcan0"],
                               cwd=tmp_path, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                               start_new_session=True)
    try:
        r = subprocess.run([*hil_command(), "run", str(suite_path.parent / suite["scenario"]), "--bus", "socketcan:vcan0",
                            "--tcu", "external", "--out", str(tmp_path), "--no-rrd", "--json", *sets],
                           capture_output=True, text=True, env=subprocess_env(), cwd=tmp_path, timeout=900)
    finally:
        tcu.terminate()
        tcu.wait(30)
    assert r.returncode == 0, r.stderr + (tmp_path / "tcu.log").read_text()[-2000:]
    s = json.loads(r.stdout)
    assert (s["bus"], s["transport"], s["suspicious"], s["rejected_frames"]) == ("socketcan:vcan0", "external", {}, {}), s
    c = subprocess.run([*hil_command(), "check", s["mcap"], str(suite_path)], capture_output=True, text=True,
                       env=subprocess_env(), timeout=300)
    verdicts = {line.split("[", 1)[1].split("]", 1)[0]: line.split(" ", 1)[0]
                for line in c.stdout.splitlines() if line.startswith(("PASS [", "FAIL ["))}
    assert {k: verdicts.get(k) for k in ("TIM-2", "ADH-1", "ADH-2")} == {"TIM-2": "PASS", "ADH-1": "PASS",
                                                                          "ADH-2": "PASS"}, c.stdout
    print(f"\nexample TCU on vcan0: {verdicts}; round trip p50 {s['round_trip_p50_us']:.0f} us, adhesion used on the "
          f"wet patch {s['adhesion_utilisation_low']:.3f}")
