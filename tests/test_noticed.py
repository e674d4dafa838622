"""Without frame authentication a run still notices what the stream itself shows to be wrong: a third
node on the local bus replays a TorqueCommand, forges an identification result before the fault and a
TCU heartbeat far ahead; the summary counts each (``suspicious``) and the log warns once per kind."""
import json
import random
import subprocess
import time

import can

from hil.bus.frames import COMMAND_ID, STATE_RUNNING, FrameCodec
from hil.bus.localbus import create_channel, remove_channel
from hil.log.read import read_log
from identifier.messages import IdentificationEvent

from .conftest import ROOT, case_seed, hil_command, subprocess_env


def test_replayed_and_forged_frames_are_counted_in_the_summary_and_warned_in_the_log(tmp_path):
    at_step = random.Random(case_seed("forging step")).randrange(200, 800)
    print(f"forging at the first command of step >= {at_step}")
    channel = create_channel()
    proc = None
    spy = can.Bus(interface="localbus", channel=channel)
    try:
        proc = subprocess.Popen(hil_command() + ["run", "scenarios/ffcc_a.toml", "--bus", f"localbus:{channel}",
                                                 "--out", str(tmp_path), "--no-rrd", "--json",
                                                 "--set", "run.duration_s=3", "--set", "run.fault_time_s=2.5",
                                                 "--set", "bus.auth=off"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(),
                                cwd=ROOT)
        codec = FrameCodec(1e-3)
        end = time.monotonic() + 120
        k = None
        while time.monotonic() < end and proc.poll() is None:
            msg = spy.recv(0.5)
            if msg is None or msg.arbitration_id != COMMAND_ID:
                continue
            frame, _ = codec.classify(msg)
            if frame is not None and frame.value.step >= at_step:
                k = frame.value.step
                spy.send(msg)                                                        # a replayed command
                spy.send(codec.result(IdentificationEvent(k, k * 1e-3, "confirmed", 0, (0.3, 0.1, 0.2, 1.0, 5.0),
                                                          0.0, 10)))               # a result before the fault
                spy.send(codec.tcu_heartbeat(0, STATE_RUNNING, k + 1000))          # a heartbeat far ahead
                break
        assert k is not None, f"the run never reached step {at_step}"
        out, err = proc.communicate(timeout=120)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        spy.shutdown()
        remove_channel(channel)
    assert proc.returncode == 0, err
    s = json.loads(out)
    noticed = s["suspicious"]
    print(noticed)
    assert noticed.get("result_before_fault", 0) >= 1 and noticed.get("heartbeat_ahead", 0) >= 1
    assert noticed.get("answered_twice", 0) + noticed.get("duplicate_command", 0) == 1
    events = [e.text for e in read_log(s["mcap"], {"/run/events"}).topic("/run/events")]
    warned = [t for t in events if t.startswith("suspicious frame (")]
    assert {t.split("(")[1].split(")")[0] for t in warned} == set(noticed)           # one warning per kind
