"""No endless lockstep run: when the TCU lives (heartbeats) but the pending step gets no command, the
plant resends the sensor frame once, then ends the run with exit 3 and one line naming the step and
the likely cause; the log is closed with the fault.  Real runs: a scenario whose motor speed leaves
the DBC's range mid-run (the TCU must reject the frame), and a third node on the local bus that forges
one sensor frame 50 steps ahead."""
import re
import subprocess
import time

import can
import pytest

from hil.bus.frames import SENSOR_ID, FrameCodec
from hil.bus.localbus import create_channel, remove_channel
from hil.log.read import read_log
from identifier.messages import SensorReading

from .conftest import ROOT, SCENARIOS, hil_command, subprocess_env

#: FFCC-a on a train already at 87 m/s with a gear ratio of 10 and no running resistance: the motor
#: starts near 1990 rad/s and accelerates past the PlantSensor frame's 2000 rad/s within the run
FAST = {"gear_ratio = 2.788": "gear_ratio = 10.0", "initial_train_speed_ms = 10.0": "initial_train_speed_ms = 87.0",
        "davis_a_n = 2600.0": "davis_a_n = 0.0", "davis_b_n_per_ms = 350.0": "davis_b_n_per_ms = 0.0",
        "davis_c_n_per_ms2 = 70.0": "davis_c_n_per_ms2 = 0.0"}


def _fast_scenario(tmp_path):
    text = (SCENARIOS / "ffcc_a.toml").read_text()
    for old, new in FAST.items():
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "fast.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("bus", ["inprocess", "local"])
def test_a_reading_out_of_the_dbc_range_ends_the_run_at_once_saying_the_wheel_ran_away(tmp_path, bus):
    """The wheel runs away (open loop): the reading the PlantSensor frame cannot carry ends the run on the plant's
    side, one line, exit 2, at the step it happened (before: the TCU rejected the frame and the lockstep run
    waited twice the progress deadline to end as a TCU that made no progress, exit 3)."""
    scenario = _fast_scenario(tmp_path)
    r = subprocess.run(hil_command() + ["run", str(scenario), "--bus", bus, "--out", str(tmp_path), "--no-rrd",
                                        "--set", "bus.auth=off"],
                       capture_output=True, text=True, env=subprocess_env(), timeout=150, cwd=ROOT)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    m = re.fullmatch(r"hil run: error: \S+: at t = ([0-9.]+) s the measured speeds \(motor 2000\.\d rad/s, train "
                     r"[0-9.]+ m/s\) leave the PlantSensor frame's range \(\+-2000 rad/s, \+-200 m/s, hil/hil.dbc\): "
                     r"the wheel ran away \(control law demand\); shorten run.duration_s or let a control law hold "
                     r"the creep", last)
    assert m, last
    log = read_log(tmp_path / "ffcc_a-gp-1.mcap")
    assert not log.damage and log.ended_early                      # closed, readable, and says it did not finish
    states = log.topic("/plant/state")
    assert states[-1].motor_speed_rad_s > 2000 > states[-2].motor_speed_rad_s - 0.5
    sent = [f for f in log.topic("/can/frames") if f.arbitration_id == SENSOR_ID and f.direction == "tx"]
    assert len(sent) == states[-1].step                            # every step before the runaway one, once
    assert abs(float(m.group(1)) - states[-1].t_s) < 1e-9


def test_a_forged_sensor_frame_from_a_third_node_ends_the_run_naming_it(tmp_path):
    """With frame authentication off, a third node on the local bus sends one PlantSensor 50 steps
    ahead: the TCU takes it and then rejects the plant's own frames as out of sequence; the plant's wait
    ends at the progress deadline.  (With authentication on, the default there, the forged frame is
    rejected as ``forged`` and the run goes on: tests/test_secoc.py.)"""
    channel = create_channel()
    proc = None
    spy = can.Bus(interface="localbus", channel=channel)
    try:
        proc = subprocess.Popen(hil_command() + ["run", "scenarios/ffcc_a.toml", "--bus", f"localbus:{channel}",
                                                 "--out", str(tmp_path), "--no-rrd", "--set", "run.duration_s=60",
                                                 "--set", "run.fault_time_s=55", "--set", "bus.lockstep_progress_s=0.5",
                                                 "--set", "bus.auth=off"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(),
                                cwd=ROOT)
        codec = FrameCodec(1e-3)
        end = time.monotonic() + 120
        forged = None
        while time.monotonic() < end and proc.poll() is None:
            msg = spy.recv(0.5)
            if msg is None or msg.arbitration_id != SENSOR_ID:
                continue
            frame, _ = codec.classify(msg)
            if frame is not None and frame.value.step >= 300:
                r = frame.value
                # the spy may lag the run by more than 50 steps (its backlog queues while it decodes): the
                # newest reading queued is the plant's step now, else the forged one lands in the past
                while (later := spy.recv(0)) is not None:
                    if later.arbitration_id == SENSOR_ID and (f := codec.classify(later)[0]) is not None:
                        r = f.value
                forged = r.step + 50
                spy.send(codec.sensor(SensorReading(forged, r.motor_speed_rad_s, r.train_speed_ms)))
                break
        assert forged is not None, "the run never reached step 300"
        _, err = proc.communicate(timeout=120)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        spy.shutdown()
        remove_channel(channel)
    assert proc.returncode == 3, err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    m = re.search(r"no command for step (\d+) within 1 s although the TCU is alive .*: the TCU's heartbeat says it is "
                  r"at step (\d+), past the plant's step (\d+): it took a sensor frame this plant did not send "
                  r"\(another node on the bus\?\)", last)
    assert m and last.startswith("hil run: error: "), last
    stuck, tcu_step = int(m.group(1)), int(m.group(2))
    assert tcu_step == forged and forged - 50 <= stuck < forged, (stuck, forged)    # stuck before the forged step
    log = read_log(tmp_path / "ffcc_a-gp-1.mcap")
    assert log.ended_early.startswith(f"fault at step {stuck}") and not log.damage
